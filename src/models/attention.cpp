#include "models/attention.h"

#include <torch/torch.h>

#include <cmath>

#include "core/error.h"

namespace dojo::models {

bool fused_attention_available() {
#if TORCH_VERSION_MAJOR >= 2
  return true;
#else
  return false;
#endif
}

namespace {
// Boolean keep-mask for causal attention with a cached prefix: [Lq, Lk].
at::Tensor causal_keep_mask(int64_t lq, int64_t lk, const at::Device& device) {
  auto ones = torch::ones({lq, lk}, torch::TensorOptions().dtype(torch::kBool).device(device));
  return torch::tril(ones, lk - lq);
}
}  // namespace

at::Tensor attention_math(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v,
                          const std::optional<at::Tensor>& mask, bool causal, std::optional<double> scale) {
  const double s = scale.value_or(1.0 / std::sqrt(static_cast<double>(q.size(-1))));
  auto scores = torch::matmul(q, k.transpose(-2, -1)) * s;  // [..., Lq, Lk]
  if (mask.has_value()) {
    if (mask->scalar_type() == torch::kBool)
      scores = scores.masked_fill(mask->logical_not(), -std::numeric_limits<float>::infinity());
    else
      scores = scores + *mask;
  }
  if (causal) {
    const auto keep = causal_keep_mask(q.size(-2), k.size(-2), q.device());
    scores = scores.masked_fill(keep.logical_not(), -std::numeric_limits<float>::infinity());
  }
  // Softmax in float32 even for half inputs: the row sums lose too much in bf16.
  const auto probs = torch::softmax(scores.to(torch::kFloat32), -1).to(v.scalar_type());  // [..., Lq, Lk]
  return torch::matmul(probs, v);                                                         // [..., Lq, Dv]
}

at::Tensor attention(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v,
                     const std::optional<at::Tensor>& mask, bool causal, std::optional<double> scale,
                     AttentionBackend backend) {
  if (backend == AttentionBackend::kMath) return attention_math(q, k, v, mask, causal, scale);
#if TORCH_VERSION_MAJOR >= 2
  std::optional<at::Tensor> full_mask = mask;
  bool fused_causal = causal;
  // The fused kernel's is_causal aligns to the top-left corner; with a cached prefix (Lq < Lk)
  // pass an explicit bottom-right-aligned mask instead.
  if (causal && (q.size(-2) != k.size(-2) || mask.has_value())) {
    auto keep = causal_keep_mask(q.size(-2), k.size(-2), q.device());
    if (mask.has_value()) {
      if (mask->scalar_type() == torch::kBool)
        keep = keep.logical_and(*mask);
      else
        keep = torch::where(keep, *mask, torch::full_like(*mask, -std::numeric_limits<float>::infinity()));
    }
    full_mask = keep;
    fused_causal = false;
  }
#if TORCH_VERSION_MAJOR > 2 || (TORCH_VERSION_MAJOR == 2 && TORCH_VERSION_MINOR >= 1)
  return at::scaled_dot_product_attention(q, k, v, full_mask, 0.0, fused_causal, scale);
#else
  // 2.0 has no scale argument: fold a non-default scale into q.
  const double default_scale = 1.0 / std::sqrt(static_cast<double>(q.size(-1)));
  const auto q_scaled = scale.has_value() ? q * (*scale / default_scale) : q;
  return at::scaled_dot_product_attention(q_scaled, k, v, full_mask, 0.0, fused_causal);
#endif
#else
  if (backend == AttentionBackend::kFused)
    throw Error("fused attention needs libtorch >= 2.0 (this build has " + std::string(TORCH_VERSION) + ")");
  return attention_math(q, k, v, mask, causal, scale);
#endif
}

}  // namespace dojo::models
