#include "diffusion/flow_matching.h"

#include <torch/torch.h>

#include <algorithm>
#include <cmath>

#include "core/error.h"
#include "test_util.h"

namespace dojo::diffusion {

namespace {

// B = 2, C = 2, T = 3, H = W = 1. Sample 0: prediction 0, target channel 0 = [0, 1, 2] over time,
// channel 1 = 0. Sample 1: prediction = target + 1 (a constant offset: no difference term).
std::pair<torch::Tensor, torch::Tensor> hand_batch() {
  auto target = torch::zeros({2, 2, 3, 1, 1});
  target[0][0].copy_(torch::tensor({0.f, 1.f, 2.f}).view({3, 1, 1}));
  target[1].copy_(torch::arange(6, torch::kFloat).view({2, 3, 1, 1}));
  auto pred = torch::zeros_like(target);
  pred[1].copy_(target[1] + 1);
  return {pred, target};
}

}  // namespace

TEST(Flow, LossTimeAxisHandValue) {
  const auto [pred, target] = hand_batch();
  FlowMatchingConfig config;  // time axis, weight 0.1
  torch::Tensor per_sample;
  const auto loss = flow_matching_loss(pred, target, config, &per_sample);
  // Sample 0: MSE (0 + 1 + 4)/6; time differences of the target: [1, 1] and [0, 0] -> mean 2/4.
  const double s0 = 5.0 / 6.0 + 0.1 * 0.5;
  ASSERT_EQ(per_sample.numel(), 2);
  EXPECT_NEAR(per_sample[0].item<double>(), s0, 1e-6);
  EXPECT_NEAR(per_sample[1].item<double>(), 1.0, 1e-6);
  EXPECT_NEAR(loss.item<double>(), (s0 + 1.0) / 2, 1e-6);
}

TEST(Flow, LossChannelAxisHandValue) {
  const auto [pred, target] = hand_batch();
  FlowMatchingConfig config;
  config.temporal_axis = TemporalAxis::kChannel;
  torch::Tensor per_sample;
  const auto loss = flow_matching_loss(pred, target, config, &per_sample);
  // Sample 0: channel difference of the target = [0, −1, −2] -> mean square 5/3.
  const double s0 = 5.0 / 6.0 + 0.1 * 5.0 / 3.0;
  EXPECT_NEAR(per_sample[0].item<double>(), s0, 1e-6);
  EXPECT_NEAR(per_sample[1].item<double>(), 1.0, 1e-6);
  EXPECT_NEAR(loss.item<double>(), (s0 + 1.0) / 2, 1e-6);
  // Weight 0 leaves the plain MSE; shape mismatch is an error.
  config.temporal_weight = 0;
  EXPECT_NEAR(flow_matching_loss(pred, target, config).item<double>(), (5.0 / 6.0 + 1.0) / 2, 1e-6);
  EXPECT_THROW(flow_matching_loss(pred, target.narrow(2, 0, 2), config), Error);
}

TEST(Flow, LossGradientFlowsToPrediction) {
  const auto [pred0, target] = hand_batch();
  auto pred = pred0.clone().requires_grad_(true);
  flow_matching_loss(pred.to(torch::kBFloat16), target, FlowMatchingConfig{}).backward();
  ASSERT_TRUE(pred.grad().defined());
  EXPECT_GT(pred.grad().abs().sum().item<double>(), 0);
}

TEST(Flow, TrainingNoiseFollowsTheInterpolation) {
  torch::manual_seed(1);
  const auto x0 = torch::randn({3, 4, 2, 3, 3});
  FlowMatchingConfig config;
  const auto n = sample_training_noise(x0, config, 42);
  ASSERT_EQ(n.sigma.sizes(), torch::IntArrayRef({3}));
  ASSERT_EQ(n.noise.sizes(), x0.sizes());
  const auto s = n.sigma.view({3, 1, 1, 1, 1});
  EXPECT_TRUE(torch::allclose(n.x_t, s * n.noise + (1 - s) * x0, 1e-6, 1e-6));
  EXPECT_TRUE(torch::allclose(n.target_velocity, n.noise - x0));
  EXPECT_TRUE(torch::allclose(n.x_t - s * n.target_velocity, x0, 1e-5, 1e-5));  // x0 = x_t − σ·v
  EXPECT_TRUE(torch::allclose(n.timesteps, 1000 * n.sigma));
  // Same seed, same draw; another seed, another draw.
  const auto again = sample_training_noise(x0, config, 42);
  EXPECT_TRUE(again.noise.equal(n.noise));
  EXPECT_TRUE(again.sigma.equal(n.sigma));
  EXPECT_FALSE(sample_training_noise(x0, config, 43).noise.equal(n.noise));
  EXPECT_THROW(sample_training_noise(x0.flatten(2), config, 1), Error);
}

TEST(Flow, TrainingTimesLieOnTheShiftedGrid) {
  FlowMatchingConfig config;
  EXPECT_DOUBLE_EQ(training_grid_sigma(0, config), 1.0);
  EXPECT_NEAR(training_grid_sigma(500, config), 2.5 / 3.0, 1e-12);  // median u = 0.5 -> σ ≈ 0.833
  const int64_t batch = 4000;
  const auto x0 = torch::zeros({batch, 1, 1, 1, 1});
  const auto n = sample_training_noise(x0, config, 7);
  const auto sigma = n.sigma.to(torch::kDouble);
  // Every σ is a grid value: invert σ = 5s/(1 + 4s) -> s = σ/(5 − 4σ), index = 1000·(1 − s).
  const auto index = 1000.0 * (1.0 - sigma / (5.0 - 4.0 * sigma));
  EXPECT_LE((index - index.round()).abs().max().item<double>(), 1e-3);
  EXPECT_NEAR(sigma.median().item<double>(), 2.5 / 3.0, 0.02);
  EXPECT_GT(sigma.min().item<double>(), 0.0);
  EXPECT_LE(sigma.max().item<double>(), 1.0);

  // High-σ strategy: p = 1 puts every time in [980, 1000]; p = 0.05 adds about 5 % there to the
  // ~1.1 % the logit-normal already puts (u < 0.093).
  config.high_sigma_prob = 1.0;
  const auto all_high = sample_training_noise(x0, config, 8);
  EXPECT_GE(all_high.timesteps.min().item<double>(), 980.0 - 1e-3);
  config.high_sigma_prob = 0.05;
  const auto some = sample_training_noise(x0, config, 9);
  const double frac = (some.timesteps >= 980.0 - 1e-3).to(torch::kDouble).mean().item<double>();
  EXPECT_GT(frac, 0.045);
  EXPECT_LT(frac, 0.08);
  config.high_sigma_prob = 1.5;
  EXPECT_THROW(sample_training_noise(x0, config, 1), Error);
}

TEST(Flow, PowerEmaGammaAndBeta) {
  const double gamma = power_ema_gamma(0.1);
  EXPECT_NEAR(gamma, 6.9372, 1e-4);
  EXPECT_NEAR(gamma * gamma * gamma + 7 * gamma * gamma - 84 * gamma - 88, 0.0, 1e-9);
  // The published relation σ_rel = sqrt((γ + 1)/((γ + 2)²(γ + 3))) holds for other values too.
  for (double sr : {0.05, 0.1, 0.2}) {
    const double g = power_ema_gamma(sr);
    EXPECT_NEAR(std::sqrt((g + 1) / ((g + 2) * (g + 2) * (g + 3))), sr, 1e-12) << sr;
  }
  EXPECT_THROW(power_ema_gamma(0.0), Error);
  EXPECT_THROW(power_ema_gamma(0.3), Error);
  EXPECT_EQ(power_ema_beta(0, gamma), 0.0);
  EXPECT_NEAR(power_ema_beta(100, gamma), 0.924, 5e-4);
  EXPECT_NEAR(power_ema_beta(1000, gamma), 0.9921, 5e-5);
  EXPECT_NEAR(power_ema_beta(10000, gamma), 0.99921, 5e-6);
}

TEST(Flow, EmaUpdateInPlaceWithoutGrad) {
  auto p = torch::tensor({1.0f, 2.0f}).requires_grad_(true);
  std::vector<torch::Tensor> params = {p};
  std::vector<torch::Tensor> ema = {torch::tensor({3.0f, -2.0f})};
  const auto storage = ema[0].data_ptr();
  ema_update(ema, params, 0.75);  // 0.75·ema + 0.25·p
  EXPECT_EQ(ema[0].data_ptr(), storage);
  EXPECT_FALSE(ema[0].requires_grad());
  EXPECT_NEAR(ema[0][0].item<double>(), 2.5, 1e-6);
  EXPECT_NEAR(ema[0][1].item<double>(), -1.0, 1e-6);
  ema_update(ema, params, power_ema_beta(0, 6.9));  // β(0) = 0 copies the weights
  EXPECT_TRUE(ema[0].equal(p.detach()));
  std::vector<torch::Tensor> wrong = {torch::zeros({3})};
  EXPECT_THROW(ema_update(wrong, params, 0.5), Error);
}

// The motion weight is 1 + strength on average over a clip's moving frames' mean change: 1 on the
// first (conditioning) frame and everywhere in a still clip, larger where the latent changes.
TEST(Flow, MotionWeightFollowsTheLatentsChange) {
  auto x0 = torch::zeros({2, 4, 3, 2, 2});                  // [B, C, T, H, W]
  x0[0].select(1, 2).select(1, 0).select(1, 0).fill_(1.0);  // sample 0: one pixel changes at t = 2
  const auto w = motion_weight(x0, 2.0);
  ASSERT_EQ(w.sizes(), (std::vector<int64_t>{2, 1, 3, 2, 2}));
  EXPECT_TRUE(w[1].eq(1.0).all().item<bool>()) << "a still clip is weighted evenly";
  EXPECT_TRUE(w[0].select(1, 0).eq(1.0).all().item<bool>());
  // Sample 0: change 1 at one of 12 (t, h, w) sites -> mean 1/12, weight there 1 + 2 * 12.
  EXPECT_NEAR(w[0][0][2][0][0].item<float>(), 25.0, 1e-4);
  EXPECT_NEAR(w[0][0][1][0][0].item<float>(), 1.0, 1e-6);
  EXPECT_NEAR(w[0].mean().item<float>(), 3.0, 1e-4);
  // A weighted loss counts the moving site more.
  const auto target = torch::zeros_like(x0);
  auto pred = torch::zeros_like(x0);
  pred[0][0][2][0][0] = 1.0;
  FlowMatchingConfig config;
  config.temporal_weight = 0;
  EXPECT_NEAR(flow_matching_loss(pred, target, config, nullptr, w).item<double>(),
              25.0 * flow_matching_loss(pred, target, config).item<double>(), 1e-5);
}

}  // namespace dojo::diffusion
