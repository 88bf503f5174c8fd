// `dojo ckpt info PATH [--json]`: what a checkpoint directory or a .safetensors file holds.
#include <CLI/CLI.hpp>
#include <cstdio>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <set>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/safetensors.h"
#include "models/dit.h"
#include "models/keypoint_probe.h"
#include "models/lam.h"
#include "models/wan_vae.h"

namespace dojo::cli {
namespace {

namespace fs = std::filesystem;

// {file, file_size, header_size, num_tensors, num_params, dtypes: {F32: {tensors, params}},
//  metadata, tensors: [{name, dtype, shape, params}]}
nlohmann::ordered_json describe(const SafetensorsFile& file) {
  nlohmann::ordered_json out;
  out["file"] = file.path().string();
  out["file_size"] = file.file_size();
  out["header_size"] = file.header_size();
  out["num_tensors"] = file.keys().size();
  out["num_params"] = file.num_elements();
  std::map<std::string, std::pair<int64_t, int64_t>> dtypes;
  nlohmann::ordered_json tensors = nlohmann::ordered_json::array();
  for (const auto& name : file.keys()) {
    const TensorInfo& info = file.info(name);
    auto& counts = dtypes[info.dtype];
    counts.first += 1;
    counts.second += info.numel();
    tensors.push_back(
        {{"name", name}, {"dtype", info.dtype}, {"shape", info.shape}, {"params", info.numel()}});
  }
  nlohmann::ordered_json dtype_json = nlohmann::ordered_json::object();
  for (const auto& [dtype, counts] : dtypes)
    dtype_json[dtype] = {{"tensors", counts.first}, {"params", counts.second}};
  out["dtypes"] = std::move(dtype_json);
  nlohmann::ordered_json metadata = nlohmann::ordered_json::object();
  for (const auto& [key, value] : file.metadata()) metadata[key] = value;
  out["metadata"] = std::move(metadata);
  out["tensors"] = std::move(tensors);
  return out;
}

nlohmann::ordered_json info_json(const fs::path& path) {
  nlohmann::ordered_json out;
  const bool is_file = fs::exists(path) ? !fs::is_directory(path) : path.extension() == ".safetensors";
  if (!is_file) {
    // A missing directory may still be a checkpoint whose save was interrupted (DIR.dojo-old).
    const Checkpoint ckpt = Checkpoint::open(path);
    out["path"] = ckpt.dir().string();
    out["format"] = "checkpoint";
    out["num_params"] = ckpt.model().num_elements();
    out["config"] = nlohmann::ordered_json::parse(ckpt.config().dump());
    out["model"] = describe(ckpt.model());
    if (ckpt.has_trainer_state()) {
      out["trainer_state"] = {{"step", ckpt.step()},
                              {"extra", nlohmann::ordered_json::parse(ckpt.trainer_extra().dump())},
                              {"tensors", describe(ckpt.trainer_tensors())}};
    } else {
      out["trainer_state"] = nullptr;
    }
    return out;
  }
  const SafetensorsFile file = SafetensorsFile::open(path);
  out["path"] = path.string();
  out["format"] = "safetensors";
  out["num_params"] = file.num_elements();
  out["model"] = describe(file);
  return out;
}

std::string with_commas(int64_t value) {
  std::string digits = std::to_string(value);
  for (int i = static_cast<int>(digits.size()) - 3; i > (value < 0 ? 1 : 0); i -= 3) digits.insert(i, ",");
  return digits;
}

std::string shorten(const std::string& text, size_t limit = 120) {
  return text.size() <= limit ? text : text.substr(0, limit - 3) + "...";
}

void print_file(const char* title, const nlohmann::ordered_json& file) {
  std::printf("%s  %s bytes, %s tensors, %s parameters\n", title,
              with_commas(file["file_size"].get<int64_t>()).c_str(),
              with_commas(file["num_tensors"].get<int64_t>()).c_str(),
              with_commas(file["num_params"].get<int64_t>()).c_str());
  for (const auto& [dtype, counts] : file["dtypes"].items())
    std::printf("  %-6s %s tensors, %s parameters\n", dtype.c_str(),
                with_commas(counts["tensors"].get<int64_t>()).c_str(),
                with_commas(counts["params"].get<int64_t>()).c_str());
  for (const auto& [key, value] : file["metadata"].items())
    std::printf("  metadata %s = %s\n", key.c_str(), shorten(value.get<std::string>()).c_str());
  size_t width = 4;
  for (const auto& tensor : file["tensors"])
    width = std::max(width, tensor["name"].get<std::string>().size());
  if (file["tensors"].empty()) return;
  std::printf("  %-*s  %-7s %s\n", static_cast<int>(width), "name", "dtype", "shape");
  for (const auto& tensor : file["tensors"])
    std::printf("  %-*s  %-7s %s\n", static_cast<int>(width), tensor["name"].get<std::string>().c_str(),
                tensor["dtype"].get<std::string>().c_str(),
                shape_string(tensor["shape"].get<std::vector<int64_t>>()).c_str());
}

void print_info(const nlohmann::ordered_json& info) {
  std::printf("%-11s %s\n", info["format"].get<std::string>().c_str(),
              info["path"].get<std::string>().c_str());
  std::printf("%-11s %s\n", "parameters", with_commas(info["num_params"].get<int64_t>()).c_str());
  if (info.contains("config"))
    std::printf("%-11s %s\n", "config", shorten(info["config"].dump(), 400).c_str());
  if (info.contains("trainer_state")) {
    const auto& trainer = info["trainer_state"];
    if (trainer.is_null()) {
      std::printf("%-11s none (inference-only checkpoint)\n", "trainer");
    } else {
      std::printf("%-11s step %s, %s tensors\n", "trainer",
                  with_commas(trainer["step"].get<int64_t>()).c_str(),
                  with_commas(trainer["tensors"]["num_tensors"].get<int64_t>()).c_str());
    }
  }
  std::printf("\n");
  print_file(info["format"] == "checkpoint" ? "model.safetensors" : "tensors", info["model"]);
}

// The model a checkpoint holds, loaded by its config.json ("model" names the family).
std::shared_ptr<torch::nn::Module> load_any_model(const fs::path& dir) {
  const auto config = Checkpoint::open(resolve_checkpoint_dir(dir)).config();
  const std::string model = config.value("model", "");
  if (model == "lam") return models::load_lam(dir).ptr();
  if (model == "wan21_vae") return models::load_tokenizer(dir).ptr();
  if (model == "action_dit") return models::load_world_model(dir).ptr();
  if (model == "keypoint_probe") return models::load_keypoint_probe(dir).ptr();
  throw Error((dir / "config.json").string() + ": unknown model '" + model +
              "' (expected lam, wan21_vae, action_dit or keypoint_probe)");
}

// A world model's checkpoint with its LoRA adapters folded into the base weights (W + alpha/r ·
// B A): plain weights, the config's other entries (action ranges, sampler, student) kept.
CheckpointData merged_world_model(const fs::path& src) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(src));
  DOJO_CHECK(ckpt.config().value("model", "") == "action_dit",
             (ckpt.dir() / "config.json").string() + ": LoRA adapters are merged into world models only");
  DOJO_CHECK(ckpt.has_adapter(), src.string() + ": no adapter_model.safetensors (no LoRA adapters to merge)");
  const auto net = models::load_world_model(src);  // folds the adapters in
  CheckpointData data = models::world_model_checkpoint(*net);
  auto config = ckpt.config();
  config["config"] = data.config["config"];
  data.config = config;
  return data;
}

// A checkpoint for inference: the same config and weights with no trainer state, the learned
// parameters stored in `dtype` (buffers such as RoPE tables keep theirs, so a bf16 export
// changes only what bf16 weights change). LoRA adapters are merged in.
void export_checkpoint(const fs::path& src, const fs::path& dst, torch::ScalarType dtype) {
  const auto module = load_any_model(src);
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(src));
  std::set<std::string> params;  // module names of the learned parameters
  for (const auto& p : module->named_parameters()) params.insert(p.key());
  CheckpointData data;
  if (ckpt.has_adapter()) {
    data = merged_world_model(src);
  } else {
    data.config = ckpt.config();
    for (const auto& name : ckpt.model().keys())
      data.model.emplace_back(name, ckpt.model().tensor(name, true));
  }
  for (auto& [name, t] : data.model) {
    // File names are the module's, possibly behind one prefix ("net.", "lam.", "probe.").
    const auto dot = name.find('.');
    const bool is_param =
        params.count(name) || (dot != std::string::npos && params.count(name.substr(dot + 1)));
    if (is_param && at::isFloatingType(t.scalar_type())) t = t.to(dtype);
  }
  save_checkpoint(dst, data);
}

}  // namespace

void register_ckpt(CLI::App& app) {
  auto* ckpt = app.add_subcommand("ckpt", "Inspect checkpoints and safetensors files");
  ckpt->require_subcommand(1);

  auto* info = ckpt->add_subcommand("info", "List the tensors, dtypes, shapes, parameter count and config");
  auto path = std::make_shared<std::string>();
  auto json = std::make_shared<bool>(false);
  info->add_option("path", *path, "Checkpoint directory or .safetensors file")->required();
  add_json_option(info, *json);
  auto* exp = ckpt->add_subcommand(
      "export",
      "Write a model checkpoint for inference: no trainer state, parameters in --dtype (buffers kept)");
  auto src = std::make_shared<std::string>(), dst = std::make_shared<std::string>(),
       dtype = std::make_shared<std::string>("bf16");
  exp->add_option("SRC", *src, "Checkpoint directory (LAM, tokenizer, world model or keypoint probe)")
      ->required();
  exp->add_option("DST", *dst, "Output checkpoint directory")->required();
  exp->add_option("--dtype", *dtype, "bf16 | fp16 | fp32")
      ->check(CLI::IsMember({"bf16", "fp16", "fp32"}))
      ->capture_default_str();
  exp->callback([src, dst, dtype] {
    set_action([src, dst, dtype] {
      const auto type = *dtype == "bf16" ? torch::kBFloat16 : *dtype == "fp16" ? torch::kHalf : torch::kFloat;
      export_checkpoint(*src, *dst, type);
      std::printf("%s -> %s (%s parameters, no trainer state)\n", src->c_str(), dst->c_str(), dtype->c_str());
      return 0;
    });
  });
  auto* merge = ckpt->add_subcommand(
      "merge", "Fold a world model's LoRA adapters into its weights (W + alpha/r · B A): a plain checkpoint");
  auto merge_src = std::make_shared<std::string>(), merge_dst = std::make_shared<std::string>();
  merge->add_option("SRC", *merge_src, "World-model checkpoint with adapter_model.safetensors")->required();
  merge->add_option("DST", *merge_dst, "Output checkpoint directory")->required();
  merge->callback([merge_src, merge_dst] {
    set_action([merge_src, merge_dst] {
      const auto data = merged_world_model(*merge_src);
      save_checkpoint(*merge_dst, data);
      std::printf("%s -> %s (LoRA adapters merged, %zu tensors)\n", merge_src->c_str(), merge_dst->c_str(),
                  data.model.size());
      return 0;
    });
  });
  info->callback([path, json] {
    set_action([path, json] {
      const auto result = info_json(*path);
      if (*json) {
        std::printf("%s\n", result.dump(2).c_str());
      } else {
        print_info(result);
      }
      return 0;
    });
  });
}

}  // namespace dojo::cli
