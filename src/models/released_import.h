// Released checkpoints -> this engine's checkpoint directories, with no Python and nothing from
// the files executed: the DreamDojo action DiT (DCP folders, model.pt, model_ema_*.pt, PEFT LoRA
// exports), the latent action model (a PyTorch Lightning .ckpt) and the Wan2.1 VAE (.pth).
//
// Facts: ../shared/reference/released_checkpoints.md. The DiT takes the EMA weights (net_ema.*,
// renamed net.*) unless `trained` asks for net.*; TransformerEngine `_extra_state` entries are
// skipped; PEFT adapters are merged (W + alpha / rank * B A) or kept beside the base weights.
// Each family's architecture is read from the tensor shapes (DitConfig::from_weights and the LAM
// and VAE equivalents here), can be corrected with config overrides, and is checked by name and
// shape against the module before anything is written.
#pragma once

#include <torch/types.h>

#include <filesystem>
#include <functional>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/safetensors.h"
#include "core/torch_file.h"

namespace dojo::models {

enum class ReleasedModel { kAuto, kDit, kLam, kWanVae };

// "auto", "dit", "lam", "wan21_vae" (throws dojo::UsageError otherwise).
ReleasedModel parse_released_model(const std::string& name);

struct ImportOptions {
  ReleasedModel model = ReleasedModel::kAuto;
  bool trained = false;    // DiT: net.* (the trained weights) instead of net_ema.*
  bool merge_lora = true;  // false: base weights in model.safetensors, adapters in adapter_model.safetensors
  double lora_alpha = 32.0;                // PEFT's alpha (the release's default); the scale is alpha / rank
  std::optional<torch::ScalarType> dtype;  // learned floating tensors cast to it; default: as stored
  std::string entry;  // the dict entry holding the weights; "" = "state_dict" when present
  nlohmann::json config_overrides = nlohmann::json::object();  // merged into the inferred config
  TorchFileOptions file;
};

struct ImportReport {
  std::string model;          // "action_dit", "lam", "wan21_vae"
  std::string source_format;  // "dcp", "zip", "legacy"
  std::string selection;      // DiT: "net_ema" or "net"
  int64_t tensors = 0;
  int64_t parameters = 0;
  int64_t lora_adapters = 0;         // adapted layers found
  std::vector<std::string> skipped;  // entries left out (_extra_state, the other weight set, ...)
  nlohmann::json config;
};

// One tensor of a released file or DCP folder, read when asked: a DCP tensor is reassembled from
// its shards by load(), a torch.save tensor is a view of the file's memory map.
struct ReleasedTensor {
  std::string name;
  std::vector<int64_t> shape;
  torch::ScalarType dtype = torch::kFloat32;
  std::function<torch::Tensor()> load;
};

// The tensors of a released file or DCP folder under their stored names (a torch.save dict is
// flattened with '.'; `options.entry` or "state_dict" picks a sub-dict), in the file's order.
// `format` receives "dcp", "zip" or "legacy".
std::vector<ReleasedTensor> released_tensors(const std::filesystem::path& source,
                                             const ImportOptions& options, std::string* format = nullptr);

// Converts `source` into a checkpoint directory at `destination` (written atomically).
ImportReport import_released(const std::filesystem::path& source, const std::filesystem::path& destination,
                             const ImportOptions& options);

// PEFT LoRA tensors (X.base_layer.weight, X.lora_A.<adapter>.weight, X.lora_B.<adapter>.weight)
// folded into X.weight = base + alpha / rank * B A (computed in fp32, stored in the base's dtype);
// X.base_layer.bias becomes X.bias. Other tensors pass through. Returns the number of layers merged.
int64_t merge_lora(NamedTensors& tensors, double alpha, const std::string& source);

}  // namespace dojo::models
