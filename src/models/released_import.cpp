#include "models/released_import.h"

#include <torch/torch.h>

#include <cmath>
#include <cstring>
#include <map>
#include <optional>
#include <set>

#include "core/checkpoint.h"
#include "core/dcp.h"
#include "core/error.h"
#include "core/log.h"
#include "core/state_dict.h"
#include "models/dit.h"
#include "models/lam.h"
#include "models/wan_vae.h"

namespace dojo::models {
namespace {

namespace fs = std::filesystem;

bool starts_with(const std::string& text, const std::string& prefix) {
  return text.compare(0, prefix.size(), prefix) == 0;
}
bool ends_with(const std::string& text, const std::string& suffix) {
  return text.size() >= suffix.size() &&
         text.compare(text.size() - suffix.size(), suffix.size(), suffix) == 0;
}

// The dict entry of a torch.save file that holds the weights.
std::string weights_entry(const TorchFile& file, const ImportOptions& options) {
  if (!options.entry.empty()) return options.entry;
  const PickleValue* state_dict = file.root().get("state_dict");  // PyTorch Lightning
  return state_dict && state_dict->kind == PickleValue::Kind::kDict ? "state_dict" : "";
}

std::string first_names(const std::vector<std::string>& names, size_t count = 5) {
  std::string text;
  for (size_t i = 0; i < names.size() && i < count; ++i) text += (i ? ", " : "") + names[i];
  if (names.size() > count) text += ", ... (+" + std::to_string(names.size() - count) + " more)";
  return text;
}

ReleasedModel detect_model(const std::vector<std::string>& names, const std::string& source) {
  for (const auto& name : names)
    if (ends_with(name, "x_embedder.proj.1.weight")) return ReleasedModel::kDit;
  for (const auto& name : names)
    if (ends_with(name, "encoder.transformer_blocks.0.spatial_attn.to_q.weight")) return ReleasedModel::kLam;
  for (const auto& name : names)
    if (ends_with(name, "decoder.head.2.weight")) return ReleasedModel::kWanVae;
  throw Error(source + ": neither a DreamDojo DiT, a LAM nor a Wan2.1 VAE (first tensors: " +
              first_names(names) + "); name the model with --model");
}

// Floating learned tensors cast to `dtype` (buffers such as RoPE tables and counters keep theirs).
void cast_floating(NamedTensors& tensors, const std::optional<torch::ScalarType>& dtype,
                   const std::set<std::string>& keep_dtype = {}) {
  if (!dtype) return;
  for (auto& [name, t] : tensors)
    if (t.is_floating_point() && !keep_dtype.count(name)) t = t.to(*dtype);
}

int64_t count_parameters(const NamedTensors& tensors) {
  int64_t n = 0;
  for (const auto& [name, t] : tensors) n += t.numel();
  return n;
}

NamedTensors load_all(const std::vector<ReleasedTensor>& tensors) {
  NamedTensors out;
  for (const auto& t : tensors) out.emplace_back(t.name, t.load());
  return out;
}

std::vector<ReleasedTensor> in_memory(const NamedTensors& tensors) {
  std::vector<ReleasedTensor> out;
  for (const auto& [name, t] : tensors)
    out.push_back({name, t.sizes().vec(), t.scalar_type(), [t] { return t; }});
  return out;
}

nlohmann::json with_overrides(nlohmann::json config, const nlohmann::json& overrides) {
  config.merge_patch(overrides);
  return config;
}

// --- the action DiT -----------------------------------------------------------------------------

ImportReport import_dit(const fs::path& source, const fs::path& destination, const std::string& format,
                        const ImportOptions& options, std::vector<ReleasedTensor> all) {
  ImportReport report;
  report.model = "action_dit";
  report.source_format = format;
  bool has_ema = false, has_net = false, has_lora = false;
  for (const auto& t : all) {
    has_ema |= starts_with(t.name, "net_ema.");
    has_net |= starts_with(t.name, "net.");
    has_lora |=
        t.name.find(".lora_A.") != std::string::npos || t.name.find(".base_layer.") != std::string::npos;
  }
  DOJO_CHECK(!options.trained || has_net,
             source.string() + ": --trained asks for net.*, which it does not hold");
  const std::string from = has_ema && !options.trained ? "net_ema." : has_net ? "net." : "";
  report.selection = from.empty() ? "unprefixed" : from.substr(0, from.size() - 1);
  std::vector<ReleasedTensor> chosen;
  for (auto& t : all) {
    if (!starts_with(t.name, from) || ends_with(t.name, "._extra_state")) {
      report.skipped.push_back(t.name);
      continue;
    }
    std::string rest = t.name.substr(from.size());
    if (starts_with(rest, "base_model.model.")) rest = rest.substr(std::strlen("base_model.model."));
    t.name = "net." + rest;
    chosen.push_back(std::move(t));
  }

  NamedTensors adapters;
  if (has_lora) {  // adapters are merged in memory; LoRA exports are inference-sized
    NamedTensors tensors = load_all(chosen);
    if (options.merge_lora) {
      report.lora_adapters = merge_lora(tensors, options.lora_alpha, source.string());
    } else {
      NamedTensors base;
      for (auto& [name, t] : tensors) {
        if (name.find(".lora_A.") != std::string::npos || name.find(".lora_B.") != std::string::npos) {
          adapters.emplace_back(name, t);
          report.lora_adapters += name.find(".lora_A.") != std::string::npos;
          continue;
        }
        const auto at = name.find(".base_layer.");
        base.emplace_back(at == std::string::npos ? name : name.substr(0, at) + name.substr(at + 11), t);
      }
      tensors = std::move(base);
    }
    chosen = in_memory(tensors);
  }

  // The architecture from the shapes alone (no tensor is read for it).
  NamedTensors shapes;
  for (const auto& t : chosen)
    shapes.emplace_back(t.name, torch::zeros({}, torch::TensorOptions().dtype(t.dtype)).expand(t.shape));
  DitConfig config = DitConfig::from_weights(shapes, "net.", source.string());
  config = DitConfig::from_json(with_overrides(config.to_json(), options.config_overrides));

  // Names and shapes must be exactly the module's; training counters may be absent.
  std::map<std::string, size_t> by_name;
  for (size_t i = 0; i < chosen.size(); ++i) by_name[chosen[i].name] = i;
  TensorStream stream;
  std::vector<std::optional<size_t>> source_index;
  std::vector<std::string> missing, mismatched;
  for (const auto& spec : dit_parameter_shapes(config)) {
    const std::string name = "net." + spec.name;
    const auto it = by_name.find(name);
    if (it == by_name.end()) {
      if (starts_with(spec.name, "accum_")) {
        stream.specs.push_back({name, spec.shape, spec.dtype});
        source_index.push_back(std::nullopt);
      } else {
        missing.push_back(name);
      }
      continue;
    }
    const ReleasedTensor& t = chosen[it->second];
    if (t.shape != spec.shape)
      mismatched.push_back(name + ": expected " + shape_string(spec.shape) + " got " + shape_string(t.shape));
    // Learned floating weights take --dtype; buffers (RoPE tables, counters) keep theirs.
    const bool cast = options.dtype && !spec.is_buffer && at::isFloatingType(t.dtype);
    stream.specs.push_back({name, t.shape, cast ? *options.dtype : t.dtype});
    source_index.push_back(it->second);
    by_name.erase(it);
  }
  std::vector<std::string> unexpected;
  for (const auto& [name, index] : by_name) unexpected.push_back(name);
  if (!missing.empty() || !unexpected.empty() || !mismatched.empty())
    throw Error(source.string() + ": does not match the DiT its shapes describe (" +
                (missing.empty() ? "" : "missing " + first_names(missing) + "; ") +
                (unexpected.empty() ? "" : "unexpected " + first_names(unexpected) + "; ") +
                (mismatched.empty() ? "" : "misshapen " + first_names(mismatched)) + ")");
  stream.produce = [specs = stream.specs, &chosen, &source_index](size_t i) -> torch::Tensor {
    const TensorSpec& spec = specs[i];
    if (!source_index[i]) return torch::zeros(spec.shape, torch::TensorOptions().dtype(spec.dtype));
    return chosen[*source_index[i]].load().to(spec.dtype);
  };
  for (const auto& spec : stream.specs) {
    int64_t numel = 1;
    for (const int64_t d : spec.shape) numel *= d;
    report.parameters += numel;
  }
  report.tensors = static_cast<int64_t>(stream.specs.size());

  CheckpointData data;
  data.config = {{"model", "action_dit"}, {"config", config.to_json()}};
  data.model_stream = std::move(stream);
  data.model_metadata["converted_from"] = source.string();
  data.model_metadata["source_format"] = report.source_format;
  data.model_metadata["weights"] = report.selection;
  if (!adapters.empty()) {  // written with the rest of the directory, crash-safe alike
    cast_floating(adapters, options.dtype);
    data.adapter = std::move(adapters);
    data.adapter_metadata["lora_alpha"] = std::to_string(options.lora_alpha);
  }
  save_checkpoint(destination, data);
  report.config = data.config;
  return report;
}

// A loaded module's checkpoint in --dtype, with where it came from, written to `destination`.
ImportReport save_converted(CheckpointData data, const fs::path& source, const fs::path& destination,
                            const ImportOptions& options, ImportReport report) {
  cast_floating(data.model, options.dtype);
  data.model_metadata["converted_from"] = source.string();
  data.model_metadata["source_format"] = report.source_format;
  save_checkpoint(destination, data);
  report.tensors = static_cast<int64_t>(data.model.size());
  report.parameters = count_parameters(data.model);
  report.config = data.config;
  return report;
}

// --- the latent action model --------------------------------------------------------------------

LamConfig lam_config_from_weights(const std::map<std::string, std::vector<int64_t>>& shapes,
                                  const std::string& source) {
  auto shape = [&](const std::string& name) {
    const auto it = shapes.find("lam." + name);
    DOJO_CHECK(it != shapes.end() && !it->second.empty(),
               "LAM weights " + source + ": no tensor 'lam." + name + "'");
    return it->second;
  };
  auto count = [&](const std::string& part) {
    int64_t n = 0;
    while (shapes.count("lam." + part + ".transformer_blocks." + std::to_string(n) +
                        ".spatial_attn.to_q.weight"))
      ++n;
    return n;
  };
  LamConfig c;
  c.model_dim = shape("encoder.ffn.1.weight")[0];
  const int64_t patch_dim = shape("encoder.ffn.0.weight")[0];
  c.patch_size = static_cast<int64_t>(std::lround(std::sqrt(patch_dim / static_cast<double>(c.in_dim))));
  DOJO_CHECK(
      c.patch_size * c.patch_size * c.in_dim == patch_dim,
      "LAM weights " + source + ": patch width " + std::to_string(patch_dim) + " is not in_dim x p x p");
  c.latent_dim = shape("fc.weight")[0] / 2;  // mean and log-variance
  c.enc_blocks = count("encoder");
  c.dec_blocks = count("decoder");
  // Rotary frequencies cover half a head.
  const int64_t head_dim = 2 * shape("encoder.transformer_blocks.0.temporal_attn.rotary_embedding.freqs")[0];
  DOJO_CHECK(head_dim > 0 && c.model_dim % head_dim == 0,
             "LAM weights " + source + ": rotary width does not divide the model width");
  c.num_heads = c.model_dim / head_dim;
  return c;
}

ImportReport import_lam(const fs::path& source, const fs::path& destination, const std::string& format,
                        const ImportOptions& options, const std::vector<ReleasedTensor>& all) {
  ImportReport report;
  report.model = "lam";
  report.source_format = format;
  bool prefixed = false;
  for (const auto& t : all) prefixed |= starts_with(t.name, "lam.");
  NamedTensors tensors;
  for (const auto& t : all) {
    if (prefixed && !starts_with(t.name, "lam."))
      report.skipped.push_back(t.name);
    else
      tensors.emplace_back(t.name, t.load());
  }
  if (!prefixed)
    for (auto& [name, t] : tensors) name = "lam." + name;
  std::map<std::string, std::vector<int64_t>> shapes;
  for (const auto& [name, t] : tensors) shapes[name] = t.sizes().vec();
  const LamConfig config = LamConfig::from_json(
      with_overrides(lam_config_from_weights(shapes, source.string()).to_json(), options.config_overrides));
  LatentActionModel model(config);
  LoadOptions load;
  load.prefix = "lam.";
  load_state_dict(*model, tensors, load);  // strict: names the tensors that do not fit
  return save_converted(lam_checkpoint(*model), source, destination, options, std::move(report));
}

// --- the Wan2.1 VAE ---------------------------------------------------------------------------

WanVaeConfig wan_config_from_weights(const std::map<std::string, std::vector<int64_t>>& shapes,
                                     const std::string& source) {
  auto shape = [&](const std::string& name) {
    const auto it = shapes.find(name);
    DOJO_CHECK(it != shapes.end() && !it->second.empty(),
               "Wan2.1 VAE weights " + source + ": no tensor '" + name + "'");
    return it->second;
  };
  WanVaeConfig c;
  c.dim = shape("encoder.conv1.weight")[0];
  c.z_dim = shape("conv2.weight")[0];
  // The encoder's downsamples: residual blocks, then a resample closing each stage but the last.
  c.dim_mult.clear();
  c.temperal_downsample.clear();
  int64_t blocks_in_stage = 0, last_width = c.dim;
  c.num_res_blocks = 0;
  for (int i = 0;; ++i) {
    const std::string layer = "encoder.downsamples." + std::to_string(i) + ".";
    if (shapes.count(layer + "residual.2.weight")) {
      last_width = shapes.at(layer + "residual.2.weight")[0];
      ++blocks_in_stage;
    } else if (shapes.count(layer + "resample.1.weight")) {
      c.dim_mult.push_back(last_width / c.dim);
      c.temperal_downsample.push_back(shapes.count(layer + "time_conv.weight") != 0);
      if (c.num_res_blocks == 0) c.num_res_blocks = blocks_in_stage;
      blocks_in_stage = 0;
    } else {
      break;
    }
  }
  c.dim_mult.push_back(last_width / c.dim);
  if (c.num_res_blocks == 0) c.num_res_blocks = blocks_in_stage;
  return c;
}

ImportReport import_wan_vae(const fs::path& source, const fs::path& destination, const std::string& format,
                            const ImportOptions& options, const std::vector<ReleasedTensor>& all) {
  ImportReport report;
  report.model = "wan21_vae";
  report.source_format = format;
  NamedTensors tensors = load_all(all);
  std::map<std::string, std::vector<int64_t>> shapes;
  for (const auto& [name, t] : tensors) shapes[name] = t.sizes().vec();
  const WanVaeConfig config = WanVaeConfig::from_json(
      with_overrides(wan_config_from_weights(shapes, source.string()).to_json(), options.config_overrides));
  WanVae vae(config);
  load_state_dict(*vae, tensors);  // strict: names the tensors that do not fit
  return save_converted(tokenizer_checkpoint(*vae), source, destination, options, std::move(report));
}

}  // namespace

ReleasedModel parse_released_model(const std::string& name) {
  if (name == "auto") return ReleasedModel::kAuto;
  if (name == "dit" || name == "action_dit") return ReleasedModel::kDit;
  if (name == "lam") return ReleasedModel::kLam;
  if (name == "wan21_vae" || name == "vae") return ReleasedModel::kWanVae;
  throw UsageError("--model: '" + name + "' is not one of auto, dit, lam, wan21_vae");
}

std::vector<ReleasedTensor> released_tensors(const fs::path& source, const ImportOptions& options,
                                             std::string* format) {
  std::vector<ReleasedTensor> out;
  if (DcpCheckpoint::is_dcp(source)) {
    const auto dcp = std::make_shared<const DcpCheckpoint>(DcpCheckpoint::open(source, options.file));
    for (const auto& entry : dcp->tensors()) {
      const DcpTensor* e = &entry;
      out.push_back({entry.name, entry.shape, entry.dtype, [dcp, e] { return dcp->tensor(*e); }});
    }
    if (format) *format = "dcp";
    return out;
  }
  DOJO_CHECK(fs::exists(source), source.string() + ": no such file or folder");
  DOJO_CHECK(!fs::is_directory(source), source.string() +
                                            ": a folder, but not a distributed checkpoint "
                                            "(no .metadata, model/.metadata or latest_checkpoint.txt)");
  const TorchFile file = TorchFile::open(source, options.file);
  for (auto& [name, t] : file.tensors(weights_entry(file, options)))
    out.push_back({name, t.sizes().vec(), t.scalar_type(), [t] { return t; }});
  if (format) *format = file.format();
  return out;
}

int64_t merge_lora(NamedTensors& tensors, double alpha, const std::string& source) {
  std::map<std::string, torch::Tensor> by_name(tensors.begin(), tensors.end());
  std::map<std::string, torch::Tensor> merged;  // X.weight -> merged weight
  std::set<std::string> consumed;
  for (const auto& [name, base] : tensors) {
    if (!ends_with(name, ".base_layer.weight")) continue;
    const std::string layer = name.substr(0, name.size() - std::strlen(".base_layer.weight"));
    std::vector<std::string> a_names;
    for (const auto& [other, t] : by_name)
      if (starts_with(other, layer + ".lora_A.") && ends_with(other, ".weight")) a_names.push_back(other);
    DOJO_CHECK(a_names.size() == 1, source + ": layer '" + layer + "' has " + std::to_string(a_names.size()) +
                                        " LoRA adapters (one is merged; keep them with --lora keep)");
    const std::string adapter = a_names[0].substr(layer.size() + 8, a_names[0].size() - layer.size() - 8 - 7);
    const std::string b_name = layer + ".lora_B." + adapter + ".weight";
    DOJO_CHECK(by_name.count(b_name), source + ": '" + a_names[0] + "' has no '" + b_name + "'");
    const torch::Tensor a = by_name.at(a_names[0]).to(torch::kFloat32);
    const torch::Tensor b = by_name.at(b_name).to(torch::kFloat32);
    DOJO_CHECK(a.dim() == 2 && b.dim() == 2 && base.dim() == 2 && b.size(1) == a.size(0) &&
                   b.size(0) == base.size(0) && a.size(1) == base.size(1),
               source + ": LoRA of '" + layer + "': base " + shape_string(base.sizes()) + ", A " +
                   shape_string(a.sizes()) + ", B " + shape_string(b.sizes()) + " do not fit W + B A");
    const double scale = alpha / static_cast<double>(a.size(0));
    merged[layer + ".weight"] = (base.to(torch::kFloat32) + scale * b.mm(a)).to(base.scalar_type());
    consumed.insert(a_names[0]);
    consumed.insert(b_name);
  }
  NamedTensors out;
  for (auto& [name, t] : tensors) {
    if (consumed.count(name)) continue;
    DOJO_CHECK(name.find(".lora_A.") == std::string::npos && name.find(".lora_B.") == std::string::npos,
               source + ": '" + name + "' is a LoRA tensor without its '.base_layer.weight'");
    if (ends_with(name, ".base_layer.weight")) {
      const std::string plain = name.substr(0, name.size() - std::strlen(".base_layer.weight")) + ".weight";
      out.emplace_back(plain, merged.at(plain));
    } else if (ends_with(name, ".base_layer.bias")) {
      out.emplace_back(name.substr(0, name.size() - std::strlen(".base_layer.bias")) + ".bias", t);
    } else {
      out.emplace_back(name, t);
    }
  }
  tensors = std::move(out);
  return static_cast<int64_t>(merged.size());
}

ImportReport import_released(const fs::path& source, const fs::path& destination,
                             const ImportOptions& options) {
  std::string format;
  std::vector<ReleasedTensor> tensors = released_tensors(source, options, &format);
  DOJO_CHECK(!tensors.empty(), source.string() + ": holds no tensors");
  std::vector<std::string> names;
  for (const auto& t : tensors) names.push_back(t.name);
  const ReleasedModel model =
      options.model == ReleasedModel::kAuto ? detect_model(names, source.string()) : options.model;
  switch (model) {
    case ReleasedModel::kDit:
      return import_dit(source, destination, format, options, std::move(tensors));
    case ReleasedModel::kLam:
      return import_lam(source, destination, format, options, tensors);
    default:
      return import_wan_vae(source, destination, format, options, tensors);
  }
}

}  // namespace dojo::models
