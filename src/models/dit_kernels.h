// Fused CPU kernels for the DiT's element-wise work between the matrix products, each with its
// own backward pass: each replaces a chain of libtorch operators that reads and writes a whole
// activation per operator (and as many backward operators) with one pass over it. A profile of
// the small DiT's sampling step put that element-wise work at a third of its time; in the
// training step it is what keeps the matrix products from the roofline (docs/benchmarks.md).
//
//   modulate           LayerNorm (no affine, eps 1e-6), then x * (1 + scale) + shift: 5 operators
//   gated_residual     x + gate * r, the gate broadcast over a frame's tokens: 2 operators
//   rms_norm_rope      per-head RMSNorm with its weight, then the rotate-half RoPE and an optional
//                      factor (the attention scale folded into the queries): about 12 operators
//
// Each has its plain libtorch path, which the network uses whenever the tensors are not float32
// on the CPU, inside a PlainDitKernelsScope, or under DOJO_PLAIN_KERNELS=1 (core/runtime.h); the
// tests compare the two on the same inputs, values and gradients.
#pragma once

#include <torch/types.h>

#include <initializer_list>

namespace dojo::models {

// Whether the fused path applies to these inputs now: all float32 on the CPU, outside a
// PlainDitKernelsScope, not DOJO_PLAIN_KERNELS=1, and not recording gradients under autocast.
bool fused_dit_kernels_apply(std::initializer_list<torch::Tensor> inputs);

// Holds this thread on the plain paths for a scope (the reference the tests compare against).
class PlainDitKernelsScope {
 public:
  PlainDitKernelsScope();
  ~PlainDitKernelsScope();
  PlainDitKernelsScope(const PlainDitKernelsScope&) = delete;
  PlainDitKernelsScope& operator=(const PlainDitKernelsScope&) = delete;
};

// x [B, T, S, D]; shift and scale broadcastable to [B, T, 1, D] (T may be 1, last dim contiguous):
// layer_norm(x) * (1 + scale) + shift, [B, T, S, D]. The fused path takes float32 only and, when
// gradients are recorded, differentiates x, shift and scale.
torch::Tensor modulate_plain(const torch::Tensor& x, const torch::Tensor& shift, const torch::Tensor& scale);
torch::Tensor modulate_fused(const torch::Tensor& x, const torch::Tensor& shift, const torch::Tensor& scale);

// x and r [B, T, S, D]; gate broadcastable to [B, T, 1, D] (as shift and scale above):
// x + gate * r, [B, T, S, D]. The fused path takes float32 only and, when gradients are recorded,
// differentiates all three.
torch::Tensor gated_residual_plain(const torch::Tensor& x, const torch::Tensor& gate, const torch::Tensor& r);
torch::Tensor gated_residual_fused(const torch::Tensor& x, const torch::Tensor& gate, const torch::Tensor& r);

// x [B, L, h, d]; weight [d]; cos and sin [L, 1, d] or undefined (no rotation): per (token, head)
// x · rsqrt(mean(x²) + eps) · weight, rotated, times `factor`. -> [B, L, h, d]. The fused path
// takes float32 x and, when gradients are recorded, differentiates x and the weight (not cos, sin).
torch::Tensor rms_norm_rope_plain(const torch::Tensor& x, const torch::Tensor& weight, double eps,
                                  const torch::Tensor& cos, const torch::Tensor& sin, double factor = 1.0);
torch::Tensor rms_norm_rope_fused(const torch::Tensor& x, const torch::Tensor& weight, double eps,
                                  const torch::Tensor& cos, const torch::Tensor& sin, double factor = 1.0);

}  // namespace dojo::models
