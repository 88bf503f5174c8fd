// Fused CPU kernels for the DiT's forward pass without gradients (sampling, streaming, the
// teacher's trajectories in distillation): each replaces a chain of libtorch operators that reads
// and writes a whole activation per operator with one pass over it. A profile of the small DiT's
// sampling step put the element-wise work between the matrix products at a third of its time.
//
//   modulate           LayerNorm (no affine, eps 1e-6), then x * (1 + scale) + shift: 5 operators
//   rms_norm_rope      per-head RMSNorm with its weight, then the rotate-half RoPE and an optional
//                      factor (the attention scale folded into the queries): about 12 operators
//
// Each has its plain libtorch path, which the network uses whenever gradients are recorded, the
// tensors are not float32 on the CPU, or DOJO_PLAIN_KERNELS=1 (core/runtime.h); the tests compare
// the two on the same inputs.
#pragma once

#include <torch/types.h>

namespace dojo::models {

// Whether the fused path applies to `x` now: float32 on the CPU, gradient recording off, and not
// DOJO_PLAIN_KERNELS=1.
bool fused_dit_kernels_apply(const torch::Tensor& x);

// Holds this thread on the plain paths for a scope: activation checkpointing runs a block without
// gradients, then again with them, and both runs must compute the same function.
class PlainDitKernelsScope {
 public:
  PlainDitKernelsScope();
  ~PlainDitKernelsScope();
  PlainDitKernelsScope(const PlainDitKernelsScope&) = delete;
  PlainDitKernelsScope& operator=(const PlainDitKernelsScope&) = delete;
};

// x [B, T, S, D]; shift and scale broadcastable to [B, T, 1, D] (T may be 1, last dim contiguous):
// layer_norm(x) * (1 + scale) + shift, [B, T, S, D].
torch::Tensor modulate_plain(const torch::Tensor& x, const torch::Tensor& shift, const torch::Tensor& scale);
torch::Tensor modulate_fused(const torch::Tensor& x, const torch::Tensor& shift, const torch::Tensor& scale);

// x [B, L, h, d]; weight [d]; cos and sin [L, 1, d] or undefined (no rotation): per (token, head)
// x · rsqrt(mean(x²) + eps) · weight, rotated, times `factor`. -> [B, L, h, d]
torch::Tensor rms_norm_rope_plain(const torch::Tensor& x, const torch::Tensor& weight, double eps,
                                  const torch::Tensor& cos, const torch::Tensor& sin, double factor = 1.0);
torch::Tensor rms_norm_rope_fused(const torch::Tensor& x, const torch::Tensor& weight, double eps,
                                  const torch::Tensor& cos, const torch::Tensor& sin, double factor = 1.0);

}  // namespace dojo::models
