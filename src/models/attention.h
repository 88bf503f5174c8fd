// Scaled dot-product attention behind one call that builds against libtorch 1.13 and 2.x.
// libtorch 2.x has a fused at::scaled_dot_product_attention (flash / memory-efficient kernels
// on GPU); 1.13 does not. attention_math() is the plain reference every path is tested against.
#pragma once

#include <ATen/core/Tensor.h>

#include <optional>

namespace dojo::models {

enum class AttentionBackend {
  kAuto,   // fused kernel when the libtorch in use has one, else math
  kMath,   // softmax(q kᵀ · scale + mask) v, always available
  kFused,  // at::scaled_dot_product_attention; throws on libtorch < 2.0
};

// True when this build's libtorch provides at::scaled_dot_product_attention.
bool fused_attention_available();

// q: [..., Lq, D], k: [..., Lk, D], v: [..., Lk, Dv] -> [..., Lq, Dv].
// mask: optional additive float mask or boolean keep-mask, broadcastable to [..., Lq, Lk].
// causal: query i attends to keys j <= i + (Lk - Lq) (the cached-prefix convention).
// scale: defaults to 1/sqrt(D).
at::Tensor attention(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v,
                     const std::optional<at::Tensor>& mask = std::nullopt, bool causal = false,
                     std::optional<double> scale = std::nullopt,
                     AttentionBackend backend = AttentionBackend::kAuto);

at::Tensor attention_math(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v,
                          const std::optional<at::Tensor>& mask = std::nullopt, bool causal = false,
                          std::optional<double> scale = std::nullopt);

}  // namespace dojo::models
