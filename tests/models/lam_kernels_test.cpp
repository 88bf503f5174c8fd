// The LAM's fused temporal attention against its plain libtorch path (attention on the transposed
// activations), values and gradients, alone and in a whole training pass.
#include "models/lam_kernels.h"

#include <gtest/gtest.h>

#include <torch/torch.h>

#include "core/autocast.h"
#include "models/dit_kernels.h"
#include "models/lam.h"
#include "test_util.h"

namespace dojo::models {
namespace {

// Output, the input's gradient and every parameter's gradient of one attention layer, for a
// given upstream gradient.
struct Pass {
  torch::Tensor out, dx;
  std::vector<torch::Tensor> dparams;
};
Pass attention_pass(LamSelfAttention& attn, const torch::Tensor& x_in, const torch::Tensor& upstream) {
  attn->zero_grad();
  auto x = x_in.detach().clone().requires_grad_(true);
  Pass p;
  p.out = attn->forward_along_axis1(x);
  (p.out * upstream).sum().backward();
  p.dx = x.grad().clone();
  for (const auto& w : attn->parameters())
    if (w.requires_grad()) p.dparams.push_back(w.grad().clone());
  return p;
}

// With and without the rotary embedding, 2 positions (the LAM's training pairs) and 5, a width that
// is not a multiple of 8 per head (12).
TEST(LamKernels, ShortAttentionValuesAndGradientsEqualThePlainPath) {
  torch::manual_seed(0);
  for (bool rotary : {true, false})
    for (int64_t L : {2, 5}) {
      LamSelfAttention attn(48, 4, 0.0, rotary);
      const auto x = torch::randn({3, L, 7, 48});
      const auto upstream = torch::randn({3, L, 7, 48});
      const auto fused = attention_pass(attn, x, upstream);
      Pass plain;
      {
        PlainDitKernelsScope scope;
        plain = attention_pass(attn, x, upstream);
      }
      EXPECT_LT(test::max_abs(fused.out, plain.out), 2e-6) << rotary << " " << L;
      EXPECT_LT(test::max_abs(fused.dx, plain.dx), 2e-5 * plain.dx.abs().max().item<double>()) << rotary << L;
      ASSERT_EQ(fused.dparams.size(), plain.dparams.size());
      for (size_t i = 0; i < plain.dparams.size(); ++i)
        EXPECT_LT(test::max_abs(fused.dparams[i], plain.dparams[i]),
                  2e-5 * plain.dparams[i].abs().max().item<double>())
            << "parameter " << i << " rotary " << rotary << " L " << L;
      // Without gradients (labelling, evaluation) the same numbers.
      torch::NoGradGuard no_grad;
      EXPECT_LT(test::max_abs(attn->forward_along_axis1(x), plain.out), 2e-6);
    }
}

// A whole training pass of the tiny LAM: the loss and every parameter's gradient agree with the
// plain path (the posterior's draw seeded alike).
TEST(LamKernels, TrainingGradientsEqualThePlainPath) {
  torch::manual_seed(1);
  LatentActionModel model(LamConfig::tiny());
  model->train();
  const auto videos = torch::rand({2, 2, 48, 64, 3});
  auto pass = [&] {
    model->zero_grad();
    torch::manual_seed(7);
    const auto loss = lam_loss(model->forward(videos), videos, 1e-3).total;
    loss.backward();
    std::vector<torch::Tensor> grads;
    for (const auto& p : model->parameters())
      if (p.requires_grad()) grads.push_back(p.grad().clone());
    return std::make_pair(loss.item<double>(), grads);
  };
  const auto fused = pass();
  std::pair<double, std::vector<torch::Tensor>> plain;
  {
    PlainDitKernelsScope scope;
    plain = pass();
  }
  EXPECT_NEAR(fused.first, plain.first, 1e-6 * std::abs(plain.first));
  ASSERT_EQ(fused.second.size(), plain.second.size());
  for (size_t i = 0; i < plain.second.size(); ++i)
    EXPECT_LT(test::max_abs(fused.second[i], plain.second[i]),
              1e-4 * plain.second[i].abs().max().item<double>())
        << "parameter " << i;
}

// The kernel alone against the formula in libtorch operators (softmax(q kᵀ · scale) v over axis 1,
// q and k rotated by interleaved pairs), whatever the network's switches say.
TEST(LamKernels, ShortAttentionIsTheFormula) {
  torch::manual_seed(2);
  const int64_t G = 2, L = 3, R = 5, heads = 2, D = 6, E = heads * D;
  const auto qkv = torch::randn({G, L, R, 3 * E});
  const auto freqs = torch::rand({D / 2});
  const auto parts = qkv.chunk(3, -1);
  auto heads_first = [&](const torch::Tensor& t) {  // [G, L, R, E] -> [G, R, heads, L, D]
    return t.reshape({G, L, R, heads, D}).permute({0, 2, 3, 1, 4});
  };
  const auto angles = torch::arange(L, torch::kFloat32).unsqueeze(1) * freqs.unsqueeze(0);  // [L, D/2]
  auto rotate = [&](const torch::Tensor& x) {
    const auto pairs = x.reshape({G, R, heads, L, D / 2, 2});
    const auto a = pairs.select(-1, 0), b = pairs.select(-1, 1);
    return torch::stack({a * angles.cos() - b * angles.sin(), b * angles.cos() + a * angles.sin()}, -1)
        .reshape({G, R, heads, L, D});
  };
  const auto q = rotate(heads_first(parts[0])), k = rotate(heads_first(parts[1])), v = heads_first(parts[2]);
  const auto probs = torch::softmax(torch::matmul(q, k.transpose(-2, -1)) * 0.3, -1);
  const auto expected = torch::matmul(probs, v).permute({0, 3, 1, 2, 4}).reshape({G, L, R, E});
  EXPECT_LT(test::max_abs(short_attention_fused(qkv, heads, freqs, 0.3), expected), 2e-6);
}

TEST(LamKernels, RefusesWhatItCannotTake) {
  const auto long_axis = torch::randn({1, kShortAttentionMaxLength + 1, 1, 12});
  EXPECT_THROW(short_attention_fused(long_axis, 2, torch::Tensor(), 1.0), std::exception);
  EXPECT_THROW(short_attention_fused(torch::randn({1, 2, 1, 12}), 5, torch::Tensor(), 1.0), std::exception);
  EXPECT_THROW(short_attention_fused(torch::randn({1, 2, 1, 12}), 2, torch::ones({3}), 1.0), std::exception);
}

// Inside the network a longer axis, and a pass under CPU autocast (whose projections are bf16),
// take the plain path instead of failing.
TEST(LamKernels, LongAxesAndAutocastTakeThePlainPath) {
  torch::manual_seed(3);
  LamSelfAttention attn(12, 2, 0.0, true);
  const auto x = torch::randn({1, kShortAttentionMaxLength + 1, 2, 12});
  const auto upstream = torch::randn_like(x);
  const auto long_pass = attention_pass(attn, x, upstream);
  Pass plain;
  {
    PlainDitKernelsScope scope;
    plain = attention_pass(attn, x, upstream);
  }
  EXPECT_TRUE(torch::equal(long_pass.out, plain.out));
  EXPECT_TRUE(torch::equal(long_pass.dx, plain.dx));

  const auto pair = torch::randn({2, 2, 3, 12});
  torch::NoGradGuard no_grad;
  const auto full = attn->forward_along_axis1(pair);
  AutocastGuard autocast(c10::DeviceType::CPU, torch::kBFloat16);
  const auto low = attn->forward_along_axis1(pair);
  EXPECT_LT(test::max_abs(low.to(torch::kFloat32), full), 0.05 * full.abs().max().item<double>());
}

}  // namespace
}  // namespace dojo::models
