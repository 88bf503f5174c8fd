// The DiT's configuration, its parameter inventory, FLOP count and checkpoint format: everything
// about the network that needs no forward pass.
#include <cmath>
#include <functional>
#include <limits>
#include <map>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/safetensors.h"
#include "core/state_dict.h"
#include "models/dit.h"

namespace dojo::models {

// ---------------------------------------------------------------------------------------------
// Config

DitConfig DitConfig::released_2b() { return DitConfig{}; }

DitConfig DitConfig::released_14b() {
  DitConfig c;
  c.model_channels = 5120;
  c.num_blocks = 36;
  c.num_heads = 40;
  return c;
}

DitConfig DitConfig::student_2b() {
  DitConfig c;
  c.max_frames = 256;
  return c;
}

DitConfig DitConfig::golden_tiny() {
  DitConfig c;
  c.model_channels = 64;
  c.num_blocks = 2;
  c.num_heads = 2;
  c.adaln_lora_dim = 16;
  c.crossattn_emb_channels = 48;
  c.crossattn_proj_dim = 32;
  c.action_dim = 8;
  // The fixture was built from freshly constructed (float32) buffers and re-randomised weights.
  c.rope_bf16_ranges = false;
  c.zero_init_action_fc2 = false;
  return c;
}

DitConfig DitConfig::small() {
  DitConfig c;
  c.model_channels = 256;
  c.num_blocks = 6;
  c.num_heads = 4;
  c.adaln_lora_dim = 64;
  c.crossattn_emb_channels = 64;
  c.crossattn_proj_dim = 64;
  c.rope_bf16_ranges = false;  // trained from scratch: no released buffers to match
  return c;
}

torch::Tensor DitConfig::action_scale_tensor() const {
  if (action_scale.empty()) return torch::ones({action_dim});
  return torch::tensor(action_scale, torch::kFloat64).to(torch::kFloat32);
}

int64_t DitConfig::patch_in_features() const {
  const int64_t channels = in_channels + 1 + (concat_padding_mask ? 1 : 0);
  return channels * patch_spatial * patch_spatial * patch_temporal;
}

int64_t DitConfig::rope_seq_len() const {
  return std::max({max_img_h / patch_spatial, max_img_w / patch_spatial, max_frames / patch_temporal});
}

nlohmann::json DitConfig::to_json() const {
  nlohmann::json j = {{"model", "dit"},
                      {"model_channels", model_channels},
                      {"num_blocks", num_blocks},
                      {"num_heads", num_heads},
                      {"adaln_lora_dim", adaln_lora_dim},
                      {"in_channels", in_channels},
                      {"out_channels", out_channels},
                      {"patch_spatial", patch_spatial},
                      {"patch_temporal", patch_temporal},
                      {"crossattn_emb_channels", crossattn_emb_channels},
                      {"crossattn_proj_dim", crossattn_proj_dim},
                      {"use_crossattn_projection", use_crossattn_projection},
                      {"max_img_h", max_img_h},
                      {"max_img_w", max_img_w},
                      {"max_frames", max_frames},
                      {"rope_h_extrapolation_ratio", rope_h_extrapolation_ratio},
                      {"rope_w_extrapolation_ratio", rope_w_extrapolation_ratio},
                      {"rope_t_extrapolation_ratio", rope_t_extrapolation_ratio},
                      {"rope_bf16_ranges", rope_bf16_ranges},
                      {"timestep_scale", timestep_scale},
                      {"action_dim", action_dim},
                      {"actions_per_latent_frame", actions_per_latent_frame},
                      {"action_hidden_dim", action_hidden_dim},
                      {"zero_init_action_fc2", zero_init_action_fc2},
                      {"action_scale", action_scale},
                      {"whole_clip_actions", whole_clip_actions},
                      {"concat_padding_mask", concat_padding_mask},
                      {"mlp_ratio", mlp_ratio}};
  if (lora.enabled()) j["lora"] = lora.to_json();  // configs without adapters keep their fingerprint
  return j;
}

DitConfig DitConfig::from_json(const nlohmann::json& j) {
  if (j.is_object() && j.contains("model"))
    DOJO_CHECK(j["model"] == "dit", "DiT config: field 'model' must be \"dit\"");
  DitConfig c;
  const JsonFields f(j, "DiT config");
  f.get("model_channels", c.model_channels);
  f.get("num_blocks", c.num_blocks);
  f.get("num_heads", c.num_heads);
  f.get("adaln_lora_dim", c.adaln_lora_dim);
  f.get("in_channels", c.in_channels);
  f.get("out_channels", c.out_channels);
  f.get("patch_spatial", c.patch_spatial);
  f.get("patch_temporal", c.patch_temporal);
  f.get("crossattn_emb_channels", c.crossattn_emb_channels);
  f.get("crossattn_proj_dim", c.crossattn_proj_dim);
  f.get("use_crossattn_projection", c.use_crossattn_projection);
  f.get("max_img_h", c.max_img_h);
  f.get("max_img_w", c.max_img_w);
  f.get("max_frames", c.max_frames);
  f.get("rope_h_extrapolation_ratio", c.rope_h_extrapolation_ratio);
  f.get("rope_w_extrapolation_ratio", c.rope_w_extrapolation_ratio);
  f.get("rope_t_extrapolation_ratio", c.rope_t_extrapolation_ratio);
  f.get("rope_bf16_ranges", c.rope_bf16_ranges);
  f.get("timestep_scale", c.timestep_scale);
  f.get("action_dim", c.action_dim);
  f.get("actions_per_latent_frame", c.actions_per_latent_frame);
  f.get("action_hidden_dim", c.action_hidden_dim);
  f.get("zero_init_action_fc2", c.zero_init_action_fc2);
  if (j.contains("action_scale")) {
    const auto& v = j["action_scale"];
    DOJO_CHECK(v.is_array() && std::all_of(v.begin(), v.end(), [](const auto& x) { return x.is_number(); }),
               "DiT config: field 'action_scale' must be a list of numbers");
    c.action_scale = v.get<std::vector<double>>();
  }
  f.get("whole_clip_actions", c.whole_clip_actions);
  f.get("concat_padding_mask", c.concat_padding_mask);
  f.get("mlp_ratio", c.mlp_ratio);
  if (j.contains("lora")) c.lora = LoraConfig::from_json(j["lora"], "DiT config");
  c.validate();
  return c;
}

DitConfig DitConfig::from_reference_kwargs(const nlohmann::json& j) {
  DitConfig c;
  const JsonFields f(j, "DiT kwargs");
  f.get("model_channels", c.model_channels);
  f.get("num_blocks", c.num_blocks);
  f.get("num_heads", c.num_heads);
  f.get("adaln_lora_dim", c.adaln_lora_dim);
  f.get("in_channels", c.in_channels);
  f.get("out_channels", c.out_channels);
  f.get("patch_spatial", c.patch_spatial);
  f.get("patch_temporal", c.patch_temporal);
  f.get("use_crossattn_projection", c.use_crossattn_projection);
  // Reference naming: crossattn_emb_channels is the width after the projection.
  if (c.use_crossattn_projection) {
    f.get("crossattn_proj_in_channels", c.crossattn_emb_channels);
    f.get("crossattn_emb_channels", c.crossattn_proj_dim);
  } else {
    f.get("crossattn_emb_channels", c.crossattn_emb_channels);
  }
  f.get("max_img_h", c.max_img_h);
  f.get("max_img_w", c.max_img_w);
  f.get("max_frames", c.max_frames);
  f.get("rope_h_extrapolation_ratio", c.rope_h_extrapolation_ratio);
  f.get("rope_w_extrapolation_ratio", c.rope_w_extrapolation_ratio);
  f.get("rope_t_extrapolation_ratio", c.rope_t_extrapolation_ratio);
  f.get("timestep_scale", c.timestep_scale);
  f.get("action_dim", c.action_dim);
  f.get("temporal_compression_ratio", c.actions_per_latent_frame);
  f.get("concat_padding_mask", c.concat_padding_mask);
  f.get("mlp_ratio", c.mlp_ratio);
  f.get("zero_init_action_embedder", c.zero_init_action_fc2);
  if (j.contains("hidden_dim_in_action_embedder") && !j["hidden_dim_in_action_embedder"].is_null())
    f.get("hidden_dim_in_action_embedder", c.action_hidden_dim);
  // A freshly constructed reference module has exact float32 RoPE ranges.
  c.rope_bf16_ranges = false;
  for (const char* key : {"extra_per_block_abs_pos_emb", "rope_enable_fps_modulation"}) {
    bool on = false;
    f.get(key, on);
    DOJO_CHECK(!on, std::string("DiT kwargs: field '") + key + "' = true is not supported");
  }
  bool adaln_lora = true;
  f.get("use_adaln_lora", adaln_lora);
  DOJO_CHECK(adaln_lora, "DiT kwargs: field 'use_adaln_lora' = false is not supported");
  c.validate();
  return c;
}

namespace {

// What from_weights reads of a set of tensors: shapes and dtypes by name.
struct WeightShapes {
  std::string source;
  std::function<const std::vector<int64_t>*(const std::string&)> shape;  // null when absent
  std::function<bool(const std::string&)> is_bf16;
};

DitConfig config_from_shapes(const WeightShapes& file, const std::string& prefix) {
  auto shape = [&](const std::string& name) -> std::vector<int64_t> {
    const std::vector<int64_t>* found = file.shape(prefix + name);
    DOJO_CHECK(found, "DiT weights " + file.source + ": no tensor '" + prefix + name + "'");
    return *found;
  };
  auto check = [&](bool ok, const std::string& name) {
    DOJO_CHECK(ok, "DiT weights " + file.source + ": unexpected shape of '" + prefix + name + "'");
  };
  DitConfig c;
  c.zero_init_action_fc2 = false;  // the weights come from the file
  const auto x_emb = shape("x_embedder.proj.1.weight");
  check(x_emb.size() == 2, "x_embedder.proj.1.weight");
  c.model_channels = x_emb[0];
  const int64_t D = c.model_channels;
  c.num_blocks = 0;
  while (file.shape(prefix + "blocks." + std::to_string(c.num_blocks) + ".self_attn.q_proj.weight"))
    ++c.num_blocks;
  DOJO_CHECK(c.num_blocks > 0,
             "DiT weights " + file.source + ": no tensor '" + prefix + "blocks.0.self_attn.q_proj.weight'");
  const int64_t head_dim = shape("blocks.0.self_attn.q_norm.weight").at(0);
  check(head_dim > 0 && D % head_dim == 0, "blocks.0.self_attn.q_norm.weight");
  c.num_heads = D / head_dim;
  c.adaln_lora_dim = shape("blocks.0.adaln_modulation_self_attn.1.weight").at(0);
  c.mlp_ratio = static_cast<double>(shape("blocks.0.mlp.layer1.weight").at(0)) / static_cast<double>(D);
  // Output p·p·16 and input (16 + 1 [+ 1])·p·p give the patch size and the padding-mask channel.
  const int64_t out_features = shape("final_layer.linear.weight").at(0);
  c.patch_spatial =
      static_cast<int64_t>(std::lround(std::sqrt(out_features / static_cast<double>(c.out_channels))));
  const int64_t pp = c.patch_spatial * c.patch_spatial;
  check(pp * c.out_channels == out_features, "final_layer.linear.weight");
  check(x_emb[1] == (c.in_channels + 2) * pp || x_emb[1] == (c.in_channels + 1) * pp,
        "x_embedder.proj.1.weight");
  c.concat_padding_mask = x_emb[1] == (c.in_channels + 2) * pp;
  c.use_crossattn_projection = file.shape(prefix + "crossattn_proj.0.weight") != nullptr;
  if (c.use_crossattn_projection) {
    const auto proj = shape("crossattn_proj.0.weight");
    c.crossattn_proj_dim = proj.at(0);
    c.crossattn_emb_channels = proj.at(1);
  } else {
    c.crossattn_emb_channels = shape("blocks.0.cross_attn.k_proj.weight").at(1);
    c.crossattn_proj_dim = c.crossattn_emb_channels;  // unused without the projection
  }
  const auto fc1 = shape("action_embedder_B_D.fc1.weight");
  check(fc1.size() == 2 && fc1[1] % c.actions_per_latent_frame == 0, "action_embedder_B_D.fc1.weight");
  c.action_dim = fc1[1] / c.actions_per_latent_frame;
  c.action_hidden_dim = fc1[0] == 4 * D ? 0 : fc1[0];
  // seq has max(max_img_h / p, max_img_w / p, max_frames) entries.
  const int64_t seq_len = shape("pos_embedder.seq").at(0);
  c.max_frames = seq_len;
  if (seq_len < c.max_img_h / c.patch_spatial) c.max_img_h = c.max_img_w = seq_len * c.patch_spatial;
  c.rope_bf16_ranges = file.is_bf16(prefix + "pos_embedder.dim_spatial_range");
  c.validate();
  return c;
}

}  // namespace

DitConfig DitConfig::from_weights(const SafetensorsFile& file, const std::string& prefix) {
  WeightShapes shapes;
  shapes.source = file.path().string();
  shapes.shape = [&file](const std::string& name) -> const std::vector<int64_t>* {
    return file.contains(name) ? &file.info(name).shape : nullptr;
  };
  shapes.is_bf16 = [&file](const std::string& name) {
    return file.contains(name) && file.info(name).dtype == "BF16";
  };
  return config_from_shapes(shapes, prefix);
}

DitConfig DitConfig::from_weights(const NamedTensors& tensors, const std::string& prefix,
                                  const std::string& source) {
  std::map<std::string, std::pair<std::vector<int64_t>, bool>> by_name;
  for (const auto& [name, t] : tensors)
    by_name[name] = {t.sizes().vec(), t.scalar_type() == torch::kBFloat16};
  WeightShapes shapes;
  shapes.source = source;
  shapes.shape = [&by_name](const std::string& name) -> const std::vector<int64_t>* {
    const auto it = by_name.find(name);
    return it == by_name.end() ? nullptr : &it->second.first;
  };
  shapes.is_bf16 = [&by_name](const std::string& name) {
    const auto it = by_name.find(name);
    return it != by_name.end() && it->second.second;
  };
  return config_from_shapes(shapes, prefix);
}

void DitConfig::validate() const {
  auto positive = [](const char* field, int64_t v) { check_positive("DiT config", field, v); };
  positive("model_channels", model_channels);
  positive("num_blocks", num_blocks);
  positive("num_heads", num_heads);
  positive("adaln_lora_dim", adaln_lora_dim);
  positive("in_channels", in_channels);
  positive("out_channels", out_channels);
  positive("patch_spatial", patch_spatial);
  positive("crossattn_emb_channels", crossattn_emb_channels);
  positive("crossattn_proj_dim", crossattn_proj_dim);
  positive("max_img_h", max_img_h);
  positive("max_img_w", max_img_w);
  positive("max_frames", max_frames);
  positive("action_dim", action_dim);
  positive("actions_per_latent_frame", actions_per_latent_frame);
  DOJO_CHECK(action_hidden_dim >= 0,
             "DiT config: field 'action_hidden_dim' must be >= 0 (0 = 4 * model_channels)");
  DOJO_CHECK(patch_temporal == 1, "DiT config: field 'patch_temporal' must be 1 (the only released value)");
  DOJO_CHECK(model_channels % num_heads == 0,
             "DiT config: field 'model_channels' must be divisible by 'num_heads'");
  DOJO_CHECK(head_dim() % 2 == 0 && head_dim() >= 6,
             "DiT config: head dim (model_channels / num_heads) must be even and >= 6 for 3-D RoPE");
  DOJO_CHECK(model_channels % 2 == 0, "DiT config: field 'model_channels' must be even");
  DOJO_CHECK(mlp_ratio > 0.0, "DiT config: field 'mlp_ratio' must be positive");
  DOJO_CHECK(action_scale.empty() || static_cast<int64_t>(action_scale.size()) == action_dim,
             "DiT config: field 'action_scale' must be empty or have action_dim (" +
                 std::to_string(action_dim) + ") entries");
  DOJO_CHECK(timestep_scale > 0.0, "DiT config: field 'timestep_scale' must be positive");
  DOJO_CHECK(
      rope_h_extrapolation_ratio > 0 && rope_w_extrapolation_ratio > 0 && rope_t_extrapolation_ratio > 0,
      "DiT config: fields 'rope_*_extrapolation_ratio' must be positive");
}

// ---------------------------------------------------------------------------------------------
// Parameter inventory (mirrors the constructors below; a test checks both agree)

std::vector<DitTensorSpec> dit_parameter_shapes(const DitConfig& c) {
  c.validate();
  const int64_t D = c.model_channels, r = c.adaln_lora_dim, d = c.head_dim();
  const auto axes = rope_axis_dims(d);
  std::vector<DitTensorSpec> out;
  auto param = [&](const std::string& name, std::vector<int64_t> shape) {
    out.push_back({name, std::move(shape), torch::kFloat32, false});
  };
  auto buffer = [&](const std::string& name, std::vector<int64_t> shape, torch::Dtype dtype) {
    out.push_back({name, std::move(shape), dtype, true});
  };
  buffer("accum_video_sample_counter", {}, torch::kInt64);
  buffer("accum_image_sample_counter", {}, torch::kInt64);
  buffer("accum_iteration", {}, torch::kInt64);
  buffer("accum_train_in_hours", {}, torch::kFloat32);
  param("x_embedder.proj.1.weight", {D, c.patch_in_features()});
  buffer("pos_embedder.seq", {c.rope_seq_len()}, torch::kFloat32);
  buffer("pos_embedder.dim_spatial_range", {axes.h / 2}, torch::kFloat32);
  buffer("pos_embedder.dim_temporal_range", {axes.t / 2}, torch::kFloat32);
  param("t_embedder.1.linear_1.weight", {D, D});
  param("t_embedder.1.linear_2.weight", {3 * D, D});
  for (int64_t i = 0; i < c.num_blocks; ++i) {
    const std::string b = "blocks." + std::to_string(i) + ".";
    for (const std::string attn : {"self_attn", "cross_attn"}) {
      const int64_t kv_in = attn == "self_attn" ? D : c.crossattn_dim();
      param(b + attn + ".q_proj.weight", {D, D});
      param(b + attn + ".q_norm.weight", {d});
      param(b + attn + ".k_proj.weight", {D, kv_in});
      param(b + attn + ".k_norm.weight", {d});
      param(b + attn + ".v_proj.weight", {D, kv_in});
      param(b + attn + ".output_proj.weight", {D, D});
    }
    param(b + "mlp.layer1.weight", {c.mlp_hidden(), D});
    param(b + "mlp.layer2.weight", {D, c.mlp_hidden()});
    for (const std::string m : {"self_attn", "cross_attn", "mlp"}) {
      param(b + "adaln_modulation_" + m + ".1.weight", {r, D});
      param(b + "adaln_modulation_" + m + ".2.weight", {3 * D, r});
    }
  }
  param("final_layer.linear.weight", {c.patch_out_features(), D});
  param("final_layer.adaln_modulation.1.weight", {r, D});
  param("final_layer.adaln_modulation.2.weight", {2 * D, r});
  param("t_embedding_norm.weight", {D});
  if (c.use_crossattn_projection) {
    param("crossattn_proj.0.weight", {c.crossattn_proj_dim, c.crossattn_emb_channels});
    param("crossattn_proj.0.bias", {c.crossattn_proj_dim});
  }
  for (const auto& [name, out_dim] : {std::pair<std::string, int64_t>{"action_embedder_B_D", D},
                                      std::pair<std::string, int64_t>{"action_embedder_B_3D", 3 * D}}) {
    param(name + ".fc1.weight", {c.action_hidden(), c.action_in_features()});
    param(name + ".fc1.bias", {c.action_hidden()});
    param(name + ".fc2.weight", {out_dim, c.action_hidden()});
    param(name + ".fc2.bias", {out_dim});
  }
  return out;
}

int64_t dit_parameter_count(const DitConfig& config) {
  int64_t n = 0;
  for (const auto& s : dit_parameter_shapes(config)) {
    if (s.is_buffer) continue;
    int64_t numel = 1;
    for (int64_t v : s.shape) numel *= v;
    n += numel;
  }
  return n;
}

double dit_forward_flops(const DitConfig& c, int64_t T, int64_t H, int64_t W, int64_t context_len) {
  const double D = static_cast<double>(c.model_channels);
  const double L = static_cast<double>(T * (H / c.patch_spatial) * (W / c.patch_spatial));  // tokens
  const double Lc = static_cast<double>(context_len), Dc = static_cast<double>(c.crossattn_dim());
  const double lora = static_cast<double>(c.adaln_lora_dim), frames = static_cast<double>(T);
  double per_block = 0;
  per_block += L * 4 * D * D;                    // self-attention q, k, v, output projections
  per_block += 2 * L * L * D;                    // scores and weighted values
  per_block += L * 2 * D * D + Lc * 2 * Dc * D;  // cross-attention q, output; k, v of the context
  per_block += 2 * L * Lc * D;                   // cross-attention scores and values
  per_block += L * 2 * D * static_cast<double>(c.mlp_hidden());  // MLP
  per_block += frames * 3 * (D * lora + lora * 3 * D);           // three modulation MLPs per frame
  double total = static_cast<double>(c.num_blocks) * per_block;
  total += L * static_cast<double>(c.patch_in_features()) * D;  // patch embedding
  total += L * D * static_cast<double>(c.patch_out_features()) + frames * (D * lora + lora * 2 * D);  // final
  total += frames * (D * D + D * 3 * D);  // timestep MLP
  total += frames * 2 * static_cast<double>(c.action_in_features() * c.action_hidden()) +
           frames * static_cast<double>(c.action_hidden()) * 4 * D;  // both action MLPs
  if (c.use_crossattn_projection)
    total += Lc * static_cast<double>(c.crossattn_emb_channels) * static_cast<double>(c.crossattn_proj_dim);
  return 2 * total;
}

// ---------------------------------------------------------------------------------------------
// Checkpoints

CheckpointData world_model_checkpoint(const ActionDitImpl& net) {
  CheckpointData data;
  data.config = {{"model", "action_dit"}, {"config", net.config.to_json()}};
  // .to(kCPU) of a CPU tensor is the tensor itself, so CPU checkpoints stay bit-exact.
  for (const auto& [name, t] : state_dict(net))
    (is_lora_name(name) ? data.adapter : data.model).emplace_back("net." + name, t.detach().to(torch::kCPU));
  // LoRA adapters apart, as PEFT keeps them; the rank is in A's shape, alpha also in the metadata.
  if (!data.adapter.empty()) {
    data.adapter_metadata["lora_alpha"] = std::to_string(net.config.lora.alpha);
    data.adapter_metadata["lora_rank"] = std::to_string(net.config.lora.rank);
  }
  return data;
}

ActionDit load_world_model(const std::filesystem::path& dir, torch::Device device) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  const auto& cfg = ckpt.config();
  DOJO_CHECK(cfg.value("model", std::string()) == "action_dit" && cfg.contains("config"),
             (ckpt.dir() / "config.json").string() + ": not a world-model checkpoint (model != action_dit)");
  auto config = DitConfig::from_json(cfg["config"]);
  LoadOptions opts;
  opts.prefix = "net.";
  if (!ckpt.has_adapter()) {
    ActionDit net(config);
    load_state_dict(*net, ckpt.model(), opts);  // strict: a mismatch throws, naming the tensors
    net->to(device);
    net->eval();
    return net;
  }
  // LoRA adapters beside the base weights (wm train --lora, convert --lora keep) are folded in:
  // W + alpha/r · B A, so inference runs plain weights at full speed.
  const std::string adapter_file = (ckpt.dir() / "adapter_model.safetensors").string();
  double alpha = config.lora.alpha;
  if (!config.lora.enabled()) {
    const auto& meta = ckpt.adapter().metadata();
    DOJO_CHECK(meta.count("lora_alpha"),
               adapter_file + ": no lora_alpha in its metadata and no lora in config.json");
    alpha = std::stod(meta.at("lora_alpha"));
  }
  auto weights = ckpt.model().tensors(/*copy=*/false);
  fold_lora(weights, ckpt.adapter().tensors(/*copy=*/false), alpha, adapter_file);
  config.lora = {};
  ActionDit net(config);
  load_state_dict(*net, weights, opts);
  net->to(device);
  net->eval();
  return net;
}

}  // namespace dojo::models
