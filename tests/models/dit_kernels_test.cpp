// The DiT's fused inference kernels against their plain libtorch paths, alone and in whole
// forward passes (with gradients recorded the network takes the plain path).
#include "models/dit_kernels.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "core/autocast.h"
#include "models/dit.h"
#include "test_util.h"

namespace dojo::models {
namespace {

TEST(DitKernels, ModulateEqualsLayerNormScaleShift) {
  torch::manual_seed(0);
  torch::NoGradGuard no_grad;
  const auto x = torch::randn({2, 3, 5, 40}) * 3 + 1;
  // The block's layout: (shift, scale, gate) chunks of one [B, T, 1, 3D] tensor (strided views),
  // per frame (T) or one for all frames (1); and a D that is no multiple of 8 (40 is).
  for (int64_t frames : {3, 1}) {
    const auto mod = torch::randn({2, frames, 1, 120}).chunk(3, -1);
    EXPECT_LT(test::max_abs(modulate_fused(x, mod[0], mod[1]), modulate_plain(x, mod[0], mod[1])), 2e-6);
  }
  const auto odd = torch::randn({1, 2, 3, 13});
  const auto mod = torch::randn({1, 2, 1, 26}).chunk(2, -1);
  EXPECT_LT(test::max_abs(modulate_fused(odd, mod[0], mod[1]), modulate_plain(odd, mod[0], mod[1])), 2e-6);
}

TEST(DitKernels, RmsNormRopeEqualsNormThenRotateHalf) {
  torch::manual_seed(1);
  torch::NoGradGuard no_grad;
  const int64_t B = 2, L = 2 * 3 * 4, H = 4, d = 32;
  const auto x = torch::randn({B, L, H, d}) * 2;
  const auto weight = 1 + 0.2 * torch::randn({d});
  const auto angles = rope_angles_3d(d, 2, 3, 4, /*frame_offset=*/5).flatten(1, 2);  // [L, 1, d]
  const auto cos = angles.cos(), sin = angles.sin();
  for (double factor : {1.0, 0.125}) {
    EXPECT_LT(test::max_abs(rms_norm_rope_fused(x, weight, 1e-6, cos, sin, factor),
                            rms_norm_rope_plain(x, weight, 1e-6, cos, sin, factor)),
              2e-6)
        << "factor " << factor;
    EXPECT_LT(test::max_abs(rms_norm_rope_fused(x, weight, 1e-6, {}, {}, factor),
                            rms_norm_rope_plain(x, weight, 1e-6, {}, {}, factor)),
              2e-6)
        << "no rotation, factor " << factor;
  }
  // The plain path is the network's own: norm, then apply_rope.
  const auto normed = x * torch::rsqrt(x.pow(2).mean(-1, true) + 1e-6) * weight;
  EXPECT_LT(test::max_abs(rms_norm_rope_plain(x, weight, 1e-6, cos, sin), apply_rope(normed, cos, sin)),
            1e-6);
}

TEST(DitKernels, ApplyOnlyToCpuFloatWithoutGradients) {
  const auto x = torch::randn({2, 2});
  {
    torch::AutoGradMode recording(true);
    EXPECT_FALSE(fused_dit_kernels_apply(x));  // a forward that may be differentiated: plain
  }
  {
    torch::NoGradGuard no_grad;
    EXPECT_TRUE(fused_dit_kernels_apply(x));
    EXPECT_FALSE(fused_dit_kernels_apply(x.to(torch::kDouble)));
  }
}

// Whole forward passes: teacher clips and a KV-cached frame, fused (no gradients) against plain
// (gradients recorded), on random weights with the action path live.
TEST(DitKernels, ForwardWithoutGradientsEqualsThePlainPath) {
  test::OneThread one_thread;
  auto c = DitConfig::small();
  c.num_blocks = 2;
  torch::manual_seed(3);
  ActionDit net(c);
  for (auto* mlp : {net->action_embedder_B_D.get(), net->action_embedder_B_3D.get()})
    mlp->fc2->reset_parameters();
  DitInputs in;
  in.x = torch::randn({2, c.in_channels, 3, 8, 8});
  in.timesteps = torch::rand({2, 3}) * 1000;
  in.condition_mask = torch::zeros({2, 1, 3, 8, 8});
  in.condition_mask.select(2, 0).fill_(1);
  in.actions = torch::randn({2, 8, c.action_dim});
  const auto plain = net->forward(in).detach();
  torch::Tensor fused;
  {
    torch::NoGradGuard no_grad;
    fused = net->forward(in);
  }
  EXPECT_LT(test::max_abs(fused, plain), 2e-5 * plain.abs().max().item<double>());

  // One more frame attending the first three through a KV cache.
  std::vector<DitKvCache> plain_cache(c.num_blocks), fused_cache(c.num_blocks);
  DitInputs frame;
  frame.x = torch::randn({2, c.in_channels, 1, 8, 8});
  frame.timesteps = torch::full({2, 1}, 500.0);
  frame.condition_mask = torch::zeros({2, 1, 1, 8, 8});
  frame.actions = torch::randn({2, 4, c.action_dim});
  frame.frame_offset = 3;
  auto run = [&](std::vector<DitKvCache>& cache) {
    DitInputs first = in;
    first.kv_cache = &cache;
    net->forward(first);
    DitInputs next = frame;
    next.kv_cache = &cache;
    return net->forward(next).detach();
  };
  const auto plain_frame = run(plain_cache);
  torch::Tensor fused_frame;
  {
    torch::NoGradGuard no_grad;
    fused_frame = run(fused_cache);
  }
  EXPECT_LT(test::max_abs(fused_frame, plain_frame), 2e-5 * plain_frame.abs().max().item<double>());
}

// Activation checkpointing recomputes each block in the backward pass: the loss and every
// gradient (weights and inputs that need one) as when every activation is kept, in float32 and
// under bf16 autocast (the backward pass runs outside the step's autocast region; the recompute
// must run as the forward did).
void expect_recomputed_gradients_equal_stored(bool bf16, double tolerance) {
  test::OneThread one_thread;
  auto c = DitConfig::small();
  c.num_blocks = 3;
  torch::manual_seed(5);
  ActionDit net(c);
  for (auto* mlp : {net->action_embedder_B_D.get(), net->action_embedder_B_3D.get()})
    mlp->fc2->reset_parameters();
  DitInputs in;
  in.x = torch::randn({2, c.in_channels, 3, 8, 8}).requires_grad_(true);
  in.timesteps = torch::rand({2, 3}) * 1000;
  in.condition_mask = torch::zeros({2, 1, 3, 8, 8});
  in.actions = torch::randn({2, 8, c.action_dim});
  auto run = [&](bool recompute) {
    net->recompute_blocks = recompute;
    net->zero_grad();
    in.x.mutable_grad() = torch::Tensor();
    torch::Tensor loss;
    {
      AutocastGuard autocast(torch::kCPU, torch::kBFloat16, bf16);
      loss = net->forward(in).to(torch::kFloat32).pow(2).mean();
    }
    loss.backward();  // outside autocast, as the trainers run it
    std::vector<torch::Tensor> grads = {in.x.grad().clone()};
    for (const auto& p : net->parameters())
      grads.push_back(p.grad().defined() ? p.grad().clone() : torch::zeros_like(p));
    return std::make_pair(loss.item<double>(), grads);
  };
  const auto [stored_loss, stored] = run(false);
  const auto [recomputed_loss, recomputed] = run(true);
  EXPECT_LE(std::abs(recomputed_loss - stored_loss), tolerance * stored_loss);
  ASSERT_EQ(stored.size(), recomputed.size());
  std::vector<std::string> names = {"input x"};
  for (const auto& p : net->named_parameters()) names.push_back(p.key());
  for (size_t i = 0; i < stored.size(); ++i) {
    const double scale = std::max(stored[i].abs().max().item<double>(), 1e-12);
    EXPECT_LE(test::max_abs(recomputed[i], stored[i]), tolerance * scale) << "gradient of " << names[i];
  }
  EXPECT_GT(stored[0].abs().max().item<double>(), 0);  // the input's gradient flowed through the blocks
}

TEST(DitCheckpointing, RecomputedBlocksGiveTheGradientsOfStoredOnes) {
  expect_recomputed_gradients_equal_stored(/*bf16=*/false, 1e-6);
}

// To float32 rounding (bit for bit here): the recompute runs the forward's ops in the forward's precision.
// Recomputed in float32, the gradients were 1.2 % off; with autocast on but the inputs' casts cached, the
// time-embedding path's were 3e-4 off.
TEST(DitCheckpointing, RecomputedBlocksUnderBf16AutocastGiveTheGradientsOfStoredOnes) {
  expect_recomputed_gradients_equal_stored(/*bf16=*/true, 1e-6);
}

}  // namespace
}  // namespace dojo::models
