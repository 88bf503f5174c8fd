// The DiT's fused kernels against their plain libtorch paths, values and gradients, alone and in
// whole forward and backward passes.
#include "models/dit_kernels.h"

#include <gtest/gtest.h>

#include <torch/torch.h>
#include <functional>
#include <optional>

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

TEST(DitKernels, ApplyToCpuFloatOutsideAPlainScope) {
  const auto x = torch::randn({2, 2});
  {
    torch::AutoGradMode recording(true);
    EXPECT_TRUE(fused_dit_kernels_apply({x}));  // with gradients: the fused backward passes
    AutocastGuard bf16(torch::kCPU, torch::kBFloat16, true);
    EXPECT_FALSE(fused_dit_kernels_apply({x}));  // bf16 training keeps libtorch's operators
  }
  {
    torch::NoGradGuard no_grad;
    EXPECT_TRUE(fused_dit_kernels_apply({x}));
    EXPECT_FALSE(fused_dit_kernels_apply({x.to(torch::kDouble)}));
    EXPECT_FALSE(fused_dit_kernels_apply({x, x.to(torch::kBFloat16)}));  // every input float32
    PlainDitKernelsScope plain;
    EXPECT_FALSE(fused_dit_kernels_apply({x}));
  }
}

// Gradients of every input that takes one, fused against plain, for a loss that weighs each
// output differently (so that a wrong reduction of a broadcast input shows).
std::vector<torch::Tensor> gradients(const std::function<torch::Tensor()>& forward,
                                     const std::vector<torch::Tensor>& inputs, const torch::Tensor& weights) {
  for (auto t : inputs) t.mutable_grad() = torch::Tensor();
  (forward() * weights).sum().backward();
  std::vector<torch::Tensor> grads;
  for (const auto& t : inputs) grads.push_back(t.grad().clone());
  return grads;
}

void expect_close(const std::vector<torch::Tensor>& fused, const std::vector<torch::Tensor>& plain,
                  double tolerance, const std::string& what) {
  ASSERT_EQ(fused.size(), plain.size());
  for (size_t i = 0; i < fused.size(); ++i) {
    const double scale = plain[i].abs().max().item<double>();
    EXPECT_GT(scale, 0) << what << ", gradient " << i;
    EXPECT_LT(test::max_abs(fused[i], plain[i]), tolerance * scale) << what << ", gradient " << i;
  }
}

TEST(DitKernels, ModulateGradientsEqualThePlainPath) {
  torch::manual_seed(6);
  // Per-frame and shared modulation (T = 1 broadcasts over frames), strided chunks of one tensor
  // as the block makes them, and a D that is not a multiple of 8.
  for (const auto& [frames, D] : std::vector<std::pair<int64_t, int64_t>>{{3, 40}, {1, 40}, {3, 13}}) {
    const auto x = (torch::randn({2, 3, 5, D}) * 3 + 1).requires_grad_(true);
    const auto mod = torch::randn({2, frames, 1, 3 * D}).requires_grad_(true);
    const auto weights = torch::randn({2, 3, 5, D});
    auto run = [&](bool fused) {
      return gradients(
          [&] {
            const auto parts = mod.chunk(3, -1);
            return fused ? modulate_fused(x, parts[0], parts[1]) : modulate_plain(x, parts[0], parts[1]);
          },
          {x, mod}, weights);
    };
    expect_close(run(true), run(false), 2e-5,
                 "frames " + std::to_string(frames) + ", D " + std::to_string(D));
  }
}

TEST(DitKernels, GatedResidualValuesAndGradientsEqualThePlainPath) {
  torch::manual_seed(9);
  for (const auto& [frames, D] : std::vector<std::pair<int64_t, int64_t>>{{3, 40}, {1, 40}, {3, 13}}) {
    const auto x = torch::randn({2, 3, 5, D}).requires_grad_(true);
    const auto r = torch::randn({2, 3, 5, D}).requires_grad_(true);
    const auto mod = torch::randn({2, frames, 1, 3 * D}).requires_grad_(true);  // the gate: a strided chunk
    const auto weights = torch::randn({2, 3, 5, D});
    const std::string what = "frames " + std::to_string(frames) + ", D " + std::to_string(D);
    {
      torch::NoGradGuard no_grad;
      const auto gate = mod.chunk(3, -1)[2];
      EXPECT_LT(test::max_abs(gated_residual_fused(x, gate, r), gated_residual_plain(x, gate, r)), 1e-6)
          << what;
    }
    auto run = [&](bool fused) {
      return gradients(
          [&] {
            const auto gate = mod.chunk(3, -1)[2];
            return fused ? gated_residual_fused(x, gate, r) : gated_residual_plain(x, gate, r);
          },
          {x, mod, r}, weights);
    };
    expect_close(run(true), run(false), 2e-6, what);
  }
}

TEST(DitKernels, RmsNormRopeGradientsEqualThePlainPath) {
  torch::manual_seed(7);
  const int64_t B = 2, L = 2 * 3 * 4, H = 4, d = 32;
  const auto angles = rope_angles_3d(d, 2, 3, 4, /*frame_offset=*/5).flatten(1, 2);  // [L, 1, d]
  const auto cos = angles.cos(), sin = angles.sin();
  const auto x = (torch::randn({B, L, H, d}) * 2).requires_grad_(true);
  const auto weight = (1 + 0.2 * torch::randn({d})).requires_grad_(true);
  const auto weights = torch::randn({B, L, H, d});
  for (bool rotate : {true, false})
    for (double factor : {1.0, 0.125}) {
      auto run = [&](bool fused) {
        return gradients(
            [&] {
              const auto c = rotate ? cos : torch::Tensor(), s = rotate ? sin : torch::Tensor();
              return fused ? rms_norm_rope_fused(x, weight, 1e-6, c, s, factor)
                           : rms_norm_rope_plain(x, weight, 1e-6, c, s, factor);
            },
            {x, weight}, weights);
      };
      const auto fused = run(true);
      expect_close(fused, run(false), 2e-5,
                   std::string(rotate ? "rotated" : "not rotated") + ", factor " + std::to_string(factor));
      // The weight's gradient sums over rows in a fixed order: the same bits on two threads.
      const int threads = at::get_num_threads();
      at::set_num_threads(2);
      const auto two = run(true);
      at::set_num_threads(threads);
      EXPECT_TRUE(torch::equal(two[1], fused[1])) << "the weight's gradient on 2 threads";
      EXPECT_TRUE(torch::equal(two[0], fused[0]));
    }
}

// Whole forward passes: teacher clips and a KV-cached frame, fused (no gradients) against plain,
// on random weights with the action path live.
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
  torch::Tensor plain, fused;
  {
    PlainDitKernelsScope reference;
    plain = net->forward(in).detach();
  }
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
  torch::Tensor plain_frame, fused_frame;
  {
    PlainDitKernelsScope reference;
    plain_frame = run(plain_cache);
  }
  {
    torch::NoGradGuard no_grad;
    fused_frame = run(fused_cache);
  }
  EXPECT_LT(test::max_abs(fused_frame, plain_frame), 2e-5 * plain_frame.abs().max().item<double>());
}

// A small DiT on random weights with its action path live, and two 3-frame clips whose input
// takes a gradient.
struct LiveDit {
  ActionDit net{nullptr};
  DitInputs in;

  LiveDit(int64_t blocks, uint64_t seed) {
    auto c = DitConfig::small();
    c.num_blocks = blocks;
    torch::manual_seed(seed);
    net = ActionDit(c);
    for (auto* mlp : {net->action_embedder_B_D.get(), net->action_embedder_B_3D.get()})
      mlp->fc2->reset_parameters();
    in.x = torch::randn({2, c.in_channels, 3, 8, 8}).requires_grad_(true);
    in.timesteps = torch::rand({2, 3}) * 1000;
    in.condition_mask = torch::zeros({2, 1, 3, 8, 8});
    in.actions = torch::randn({2, 8, c.action_dim});
  }
};

// A whole training pass: the loss and every gradient (weights and the input) with the fused
// backward passes against the plain operators'.
TEST(DitKernels, TrainingGradientsEqualThePlainPath) {
  test::OneThread one_thread;
  LiveDit live(/*blocks=*/2, /*seed=*/8);
  auto& [net, in] = live;
  std::vector<torch::Tensor> inputs = {in.x};
  for (const auto& p : net->parameters()) inputs.push_back(p);
  auto run = [&](bool fused) {
    std::optional<PlainDitKernelsScope> plain;
    if (!fused) plain.emplace();
    for (auto t : inputs) t.mutable_grad() = torch::Tensor();
    const auto loss = net->forward(in).pow(2).mean();
    loss.backward();
    std::vector<torch::Tensor> grads = {loss.detach().reshape({1})};
    for (const auto& t : inputs)
      grads.push_back(t.grad().defined() ? t.grad().clone() : torch::zeros_like(t));
    return grads;
  };
  const auto fused = run(true), plain = run(false);
  ASSERT_EQ(fused.size(), plain.size());
  std::vector<std::string> names = {"loss", "input x"};
  for (const auto& p : net->named_parameters()) names.push_back(p.key());
  for (size_t i = 0; i < fused.size(); ++i) {
    const double scale = std::max(plain[i].abs().max().item<double>(), 1e-12);
    EXPECT_LE(test::max_abs(fused[i], plain[i]), 1e-4 * scale) << names[i];
  }
  EXPECT_GT(plain[1].abs().max().item<double>(), 0);  // the gradient flowed through the blocks
}

// Activation checkpointing recomputes each block in the backward pass: the loss and every
// gradient (weights and inputs that need one) as when every activation is kept, in float32 and
// under bf16 autocast (the backward pass runs outside the step's autocast region; the recompute
// must run as the forward did).
void expect_recomputed_gradients_equal_stored(bool bf16, double tolerance) {
  test::OneThread one_thread;
  LiveDit live(/*blocks=*/3, /*seed=*/5);
  auto& [net, in] = live;
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
