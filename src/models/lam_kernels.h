// A fused CPU kernel for the LAM's temporal attention, with its own backward pass.
//
// The LAM's encoder attends over time for every token position: 2 frames at a time in training,
// so each (sample, position, head) is a 2x2 attention over 32 numbers per head. libtorch runs it
// as a transpose of the activations into [(B S), T, E], the interleaved rotary embedding (about
// 15 operators on q and as many on k), two batched products of 1568 tiny matrices, a softmax and
// a transpose back, each recorded for the backward pass: on the small LAM that was about 3 ms of
// each encoder block against 1 ms of useful products (docs/benchmarks.md). Here one pass reads
// the projections where the linear layer wrote them, in the frames' own layout, and writes the
// attention's output in that layout; the backward pass is one pass too.
//
// The plain reference is LamSelfAttentionImpl::forward on the transposed activations (models/lam);
// the network takes it whenever the tensors are not float32 on the CPU, inside a
// PlainDitKernelsScope, or under DOJO_PLAIN_KERNELS=1 (models/dit_kernels.h), and the tests
// compare the two, values and gradients.
#pragma once

#include <torch/types.h>

namespace dojo::models {

// The longest attended axis the fused kernel takes (longer ones: the plain path).
constexpr int64_t kShortAttentionMaxLength = 16;

// qkv [G, L, R, 3E] float32 (the fused q, k, v projections of [G, L, R, E] activations, E = heads
// * head_dim, q then k then v along the last axis); attention over L for every (g, r, head),
// softmax(q kᵀ · scale) v, with q and k first rotated by the interleaved rotary embedding at
// positions 0..L-1 when `freqs` [head_dim / 2] is defined. -> [G, L, R, E]. L <=
// kShortAttentionMaxLength; differentiates qkv when gradients are recorded (not freqs).
torch::Tensor short_attention_fused(const torch::Tensor& qkv, int64_t heads, const torch::Tensor& freqs,
                                    double scale);

}  // namespace dojo::models
