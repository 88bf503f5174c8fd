// LoRA adapters on the DiT's linear layers, in PEFT's layout: a frozen layer y = W x gains
// y = W x + (alpha / r) · B (A x), A [r, in] (PyTorch's Linear init), B [out, r] (zeros, so a fresh
// adapter changes nothing). The adapters are registered under the layer they adapt, so their
// parameters are named as PEFT names them: "<layer>.lora_A.default.weight", "<layer>.lora_B.default.
// weight". Checkpoints keep them apart from the base weights (adapter_model.safetensors); loading
// for inference folds them in (W + alpha/r · B A), so the streaming engine runs plain weights.
#pragma once

#include <torch/nn/module.h>
#include <torch/nn/modules/linear.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

namespace dojo::models {

using NamedTensors = std::vector<std::pair<std::string, torch::Tensor>>;

struct LoraConfig {
  int64_t rank = 0;     // 0: no adapters
  double alpha = 32.0;  // the release's PEFT default (rank 32, alpha 32)
  // Short names of the adapted layers in every block's self- and cross-attention and MLP:
  // q, k, v, o (q_proj, k_proj, v_proj, output_proj), mlp1, mlp2 (mlp.layer1, mlp.layer2).
  std::vector<std::string> targets = {"q", "k", "v", "o", "mlp1", "mlp2"};

  bool enabled() const { return rank > 0; }
  double scale() const { return alpha / static_cast<double>(rank); }
  bool targets_layer(const std::string& short_name) const;
  nlohmann::json to_json() const;
  // Throws dojo::Error naming `where` and the field on a bad value.
  static LoraConfig from_json(const nlohmann::json& j, const std::string& where);
  // "q,k,v,o,mlp1,mlp2" -> targets; throws dojo::Error on an unknown name.
  static std::vector<std::string> parse_targets(const std::string& list);
};

// One adapted layer's pair; undefined modules when the layer is not adapted.
struct LoraAdapter {
  torch::nn::Linear down{nullptr};  // lora_A: in -> r
  torch::nn::Linear up{nullptr};    // lora_B: r -> out
  double scale = 0;
  bool active() const { return !down.is_empty(); }
};

// Registers lora_A.default and lora_B.default under `layer` when `config` targets `short_name`;
// returns the pair (inactive otherwise).
LoraAdapter attach_lora(torch::nn::Linear& layer, const std::string& short_name, const LoraConfig& config);

// layer(x), plus the adapter's scale · B (A x) when it is active.
inline torch::Tensor lora_forward(const torch::nn::Linear& layer, const LoraAdapter& adapter,
                                  const torch::Tensor& x) {
  auto y = layer.ptr()->forward(x);
  if (adapter.active()) y = y + adapter.up.ptr()->forward(adapter.down.ptr()->forward(x)) * adapter.scale;
  return y;
}

// Whether a parameter name is a LoRA adapter's ("....lora_A.<name>.weight" / "lora_B").
bool is_lora_name(const std::string& name);

// Splits a state dict into base weights and adapters.
std::pair<NamedTensors, NamedTensors> split_lora(NamedTensors tensors);

// Folds adapters ("X.lora_A.<name>.weight", "X.lora_B.<name>.weight") into the base tensors'
// "X.weight": W + alpha / rank · B A (fp32 arithmetic, the base's dtype). Throws dojo::Error
// naming `source` when an adapter has no base or the shapes do not fit.
void fold_lora(NamedTensors& base, const NamedTensors& adapters, double alpha, const std::string& source);

}  // namespace dojo::models
