#include "train/self_forcing.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "core/autocast.h"
#include "core/state_dict.h"
#include "test_util.h"
#include "wm_test_fixtures.h"

namespace dojo::train {
namespace {

using test_fixtures::gen;

// The rollout distillation trains on is the one the streaming engine runs: same noise, same
// latents (the growing cache trimmed to the window against the engine's ring), with and without
// an attention sink.
TEST(SelfForcing, TrainingRolloutEqualsTheStreamingEngine) {
  test::OneThread one;
  torch::manual_seed(0);
  models::ActionDit net(test_fixtures::tiny_dit(/*live_actions=*/true));
  models::WanVae vae(models::WanVaeConfig::tiny());
  const auto first = torch::randint(0, 255, {1, 32, 32, 3}, torch::kByte);
  const auto actions = torch::rand({1, 24, 384}, gen(1)) * 2 - 1;  // 6 steps
  std::vector<torch::Tensor> rollouts;
  for (const auto& [sink, position] :
       std::vector<std::pair<int64_t, infer::SinkPosition>>{{0, infer::SinkPosition::kWindowEdge},
                                                            {1, infer::SinkPosition::kWindowEdge},
                                                            {1, infer::SinkPosition::kAbsolute},
                                                            {2, infer::SinkPosition::kWindowEdge}}) {
    infer::StreamingEngine::Options o;
    o.decode = false;
    o.student.window_frames = 2;
    o.student.sink_frames = sink;
    o.student.sink_position = position;
    infer::StreamingEngine engine(net, vae, o);
    engine.reset(first, 11);
    std::vector<torch::Tensor> streamed;
    for (int64_t s = 0; s < 6; ++s) streamed.push_back(engine.step(actions.narrow(1, 4 * s, 4)));

    torch::NoGradGuard no_grad;
    const auto z0 =
        engine.tokenizer()->encode_latents(models::video_to_model(first.unsqueeze(1)));  // [1, 16, 1, 4, 4]
    auto g = gen(11);  // the engine's draws: one ε per new frame, in order
    std::vector<torch::Tensor> noise = {torch::zeros_like(z0)};
    for (int64_t s = 0; s < 6; ++s) noise.push_back(torch::randn(z0.sizes(), g));
    const auto rolled = student_rollout(*net, o.student, z0, actions, torch::cat(noise, 2), 3, 7);
    ASSERT_EQ(rolled.size(2), 7);
    EXPECT_LT((rolled.narrow(2, 1, 6) - torch::cat(streamed, 2)).abs().max().item<double>(), 1e-4)
        << "sink " << sink << " " << infer::to_string(position);
    rollouts.push_back(rolled);
    if (sink > 0) continue;
    // An earlier exit is a different (noisier) sample.
    const auto early = student_rollout(*net, o.student, z0, actions, torch::cat(noise, 2), 0, 7);
    EXPECT_GT((early - rolled).abs().max().item<double>(), 1e-3);
  }
  // They differ once frame 0 leaves the window (frame 3 on), so each comparison can fail.
  for (size_t i = 1; i < rollouts.size(); ++i)
    EXPECT_GT((rollouts[i - 1] - rollouts[i]).narrow(2, 3, 4).abs().max().item<double>(), 1e-3) << i;
}

// Under bf16 autocast the rollout's passes without gradients (the re-cache, the earlier hops) cache
// bf16 copies of the weights (CUDA autocast does; libtorch 1.13's CPU autocast caches nothing, so
// only the CUDA test can catch a reused copy); the pass that trains must not reuse them, or the
// student's linear weights get no gradient at all.
void expect_bf16_rollout_gradients(torch::Device device) {
  test::OneThread one;
  torch::manual_seed(0);
  models::ActionDit net(test_fixtures::tiny_dit(/*live_actions=*/true));
  net->to(device);
  infer::StudentConfig config;
  config.window_frames = 2;
  const int64_t frames = 4;
  const auto first = torch::randn({1, 16, 1, 4, 4}, gen(2)).to(device);
  const auto actions = (torch::rand({1, 4 * (frames - 1), 384}, gen(3)) * 2 - 1).to(device);
  const auto noise = torch::randn({1, 16, frames, 4, 4}, gen(4)).to(device);
  torch::Tensor loss;
  {
    AutocastGuard autocast(device.type(), Precision::kBFloat16);
    const auto rolled = student_rollout(*net, config, first, actions, noise, /*exit_hop=*/2, frames - 1);
    loss = rolled.narrow(2, frames - 1, 1).pow(2).mean();
  }
  loss.backward();
  int64_t linear_weights = 0;
  for (const auto& item : net->named_parameters()) {
    if (item.key().find("blocks.0.self_attn.") == std::string::npos ||
        item.key().find(".weight") == std::string::npos)
      continue;
    ++linear_weights;
    ASSERT_TRUE(item.value().grad().defined()) << item.key();
    EXPECT_GT(item.value().grad().abs().sum().item<double>(), 0) << item.key() << " got no gradient";
  }
  EXPECT_GE(linear_weights, 3) << "the attention's projections were found";
}

TEST(SelfForcing, Bf16RolloutsBackpropagateIntoTheStudentsWeights) {
  expect_bf16_rollout_gradients(torch::kCPU);
}

TEST(SelfForcing, Bf16RolloutsBackpropagateIntoTheStudentsWeights_CUDA) {
  DOJO_REQUIRE_CUDA();
  expect_bf16_rollout_gradients(torch::kCUDA);
}

// With the critic equal to the teacher the scores agree: no generator gradient. A critic trained
// on the student's samples lowers its loss.
TEST(SelfForcing, DmdVanishesAtAPerfectCriticAndTheCriticLearns) {
  test::OneThread one;
  torch::manual_seed(1);
  models::ActionDit teacher(test_fixtures::tiny_dit(/*live_actions=*/true));
  models::ActionDit critic(teacher->config);
  load_state_dict(*critic, state_dict(*teacher));
  const auto window = torch::randn({2, 16, 4, 4, 4}, gen(2)).requires_grad_(true);
  const auto actions = torch::rand({2, 12, 384}, gen(3));
  const auto sigma = torch::tensor({0.3f, 0.8f});
  const auto noise = torch::randn({2, 16, 4, 4, 4}, gen(4));
  auto loss = dmd_generator_loss(*teacher, *critic, window, actions, sigma, noise);
  loss.backward();
  EXPECT_EQ(loss.item<double>(), 0.0);
  EXPECT_EQ(window.grad().abs().max().item<double>(), 0.0);

  torch::optim::Adam opt(critic->parameters(), torch::optim::AdamOptions(1e-3));
  const auto w = window.detach();
  const double before = critic_loss(*critic, w, actions, sigma, noise).item<double>();
  for (int i = 0; i < 30; ++i) {
    opt.zero_grad();
    critic_loss(*critic, w, actions, sigma, noise).backward();
    opt.step();
  }
  const double after = critic_loss(*critic, w, actions, sigma, noise).item<double>();
  EXPECT_LT(after, 0.5 * before);
  // Now the scores differ, and the generator gets a gradient.
  window.mutable_grad() = torch::Tensor();
  dmd_generator_loss(*teacher, *critic, window, actions, sigma, noise).backward();
  EXPECT_GT(window.grad().abs().max().item<double>(), 0.0);
}

}  // namespace
}  // namespace dojo::train
