#include "infer/world_model.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "core/checkpoint.h"
#include "core/error.h"
#include "infer/generator.h"
#include "test_util.h"
#include "train/wm_test_fixtures.h"

namespace dojo::infer {
namespace {

WorldModel random_model() {
  torch::manual_seed(0);
  return WorldModel(models::ActionDit(train::test_fixtures::tiny_dit(/*live_actions=*/true, /*width=*/32)),
                    models::WanVae(models::WanVaeConfig::tiny()));
}

TEST(WorldModel, RolloutChainsChunksDeterministically) {
  test::OneThread one;
  auto model = random_model();
  const auto first = torch::randint(0, 255, {2, 16, 16, 3}, torch::kByte);
  const auto actions = torch::rand({2, 24, 384}) * 2 - 1;
  SamplerOptions s;
  s.steps = 3;
  const auto a = model.rollout(first, actions, 7, s, ConcatMode::kAligned);
  EXPECT_EQ(a.sizes(), (std::vector<int64_t>{2, 25, 16, 16, 3}));
  EXPECT_EQ(a.scalar_type(), torch::kUInt8);
  EXPECT_TRUE(a.equal(model.rollout(first, actions, 7, s, ConcatMode::kAligned))) << "same seed, same video";
  EXPECT_FALSE(a.equal(model.rollout(first, actions, 8, s, ConcatMode::kAligned)));

  // Frame 0 is the tokenizer's version of the first frame.
  EXPECT_TRUE(a.select(1, 0).equal(model.reconstruct_frames(first)));

  // The released joining keeps each later chunk's re-decoded conditioning frame (so frame 13
  // is the round trip of frame 12) and drops its last frame; the first chunk is shared.
  const auto r = model.rollout(first, actions, 7, s, ConcatMode::kReleased);
  EXPECT_EQ(r.sizes(), a.sizes());
  EXPECT_TRUE(r.narrow(1, 0, 13).equal(a.narrow(1, 0, 13)));
  const auto round_trip = model.reconstruct_frames(a.select(1, 12).contiguous());
  EXPECT_LE((r.select(1, 13).to(torch::kInt) - round_trip.to(torch::kInt)).abs().max().item<int>(), 1);
  EXPECT_TRUE(r.narrow(1, 14, 11).equal(a.narrow(1, 13, 11)));
}

// The evaluation's ceiling: ground truth cut and joined like a rollout. Each chunk is a round
// trip of its own 13 frames (frame 12 of one chunk is frame 0 of the next, encoded alone), not a
// slice of one long round trip.
TEST(WorldModel, ChunkedRoundTripMatchesTheRolloutLayout) {
  test::OneThread one;
  auto model = random_model();
  const auto video = torch::randint(0, 255, {1, 25, 16, 16, 3}, torch::kByte);
  const auto aligned = model.reconstruct_chunks(video, ConcatMode::kAligned);
  ASSERT_EQ(aligned.sizes(), video.sizes());
  const auto c0 = model.reconstruct_video(video.narrow(1, 0, 13));
  const auto c1 = model.reconstruct_video(video.narrow(1, 12, 13));
  EXPECT_TRUE(aligned.narrow(1, 0, 13).equal(c0));
  EXPECT_TRUE(aligned.narrow(1, 13, 12).equal(c1.narrow(1, 1, 12)));
  const auto released = model.reconstruct_chunks(video, ConcatMode::kReleased);
  EXPECT_TRUE(released.narrow(1, 13, 12).equal(c1.narrow(1, 0, 12)));
  // Different from one causal pass over all 25 frames: the chunks restart the tokenizer's caches.
  EXPECT_FALSE(aligned.equal(model.reconstruct_video(video)));
  EXPECT_THROW(model.reconstruct_chunks(video.narrow(1, 0, 13 + 4)), Error);
}

TEST(WorldModel, ActionsChangeThePrediction) {
  test::OneThread one;
  auto model = random_model();
  const auto first = torch::randint(0, 255, {1, 16, 16, 3}, torch::kByte);
  SamplerOptions s;
  s.steps = 2;
  const auto a = model.predict_chunk(first, torch::zeros({1, 12, 384}), 1, s);
  const auto b = model.predict_chunk(first, torch::ones({1, 12, 384}), 1, s);
  EXPECT_EQ(a.sizes(), (std::vector<int64_t>{1, 13, 16, 16, 3}));
  EXPECT_FALSE(a.narrow(1, 1, 12).equal(b.narrow(1, 1, 12)));
  EXPECT_TRUE(a.select(1, 0).equal(b.select(1, 0))) << "the conditioning frame does not depend on actions";
}

TEST(WorldModel, RejectsBadShapesClearly) {
  auto model = random_model();
  const auto first = torch::zeros({1, 16, 16, 3}, torch::kByte);
  EXPECT_NE(test::error_message([&] {
              model.rollout(first, torch::zeros({1, 10, 384}), 0);
            }).find("multiple of 12"),
            std::string::npos);
  EXPECT_NE(test::error_message([&] {
              model.predict_chunk(first.to(torch::kFloat), torch::zeros({1, 12, 384}), 0);
            }).find("uint8"),
            std::string::npos);
  EXPECT_EQ(parse_solver("euler"), diffusion::Solver::kEuler);
  EXPECT_NE(test::error_message([] { parse_solver("ddim"); }).find("ddim"), std::string::npos);
  EXPECT_NE(test::error_message([] { parse_concat_mode("x"); }).find("aligned"), std::string::npos);
}

}  // namespace
// Action guidance extrapolates from the zero-action prediction toward the action one: scale 1 is
// the plain sampler and scale 0 is the rollout with zero actions.
TEST(WorldModel, ActionGuidanceInterpolatesBetweenZeroAndTrueActions) {
  test::OneThread one;
  auto model = random_model();
  const auto first = torch::randint(0, 255, {1, 16, 16, 3}, torch::kByte);
  const auto actions = torch::rand({1, 12, 384}) * 2 - 1;
  SamplerOptions plain;
  plain.steps = 3;
  auto guided = plain;
  guided.action_guidance = 1.0 + 1e-9;  // through the batched branch
  const auto a = model.rollout(first, actions, 3, plain, ConcatMode::kAligned);
  const auto b = model.rollout(first, actions, 3, guided, ConcatMode::kAligned);
  EXPECT_LE((a.to(torch::kInt) - b.to(torch::kInt)).abs().max().item<int>(), 1);
  guided.action_guidance = 0.0;
  const auto zero = model.rollout(first, torch::zeros_like(actions), 3, plain, ConcatMode::kAligned);
  const auto c = model.rollout(first, actions, 3, guided, ConcatMode::kAligned);
  EXPECT_LE((zero.to(torch::kInt) - c.to(torch::kInt)).abs().max().item<int>(), 1);
  guided.action_guidance = 3.0;
  EXPECT_FALSE(model.rollout(first, actions, 3, guided, ConcatMode::kAligned).equal(a));
}

// A loaded world model carries what its checkpoint records of training: the time shift its
// sampler defaults to and the action ranges rollouts normalise with; older checkpoints have
// neither and get the defaults.
TEST(WorldModel, LoadKeepsTheTrainedShiftAndActionRanges) {
  test::OneThread one;
  test::TempDir tmp;
  torch::manual_seed(0);
  models::ActionDit net(train::test_fixtures::tiny_dit(/*live_actions=*/true, /*width=*/32));
  models::WanVae vae(models::WanVaeConfig::tiny());
  models::save_tokenizer(tmp / "tok", *vae);
  auto data = models::world_model_checkpoint(*net);
  save_checkpoint(tmp / "plain", data);
  const nlohmann::json ranges = {{"dojosim_robot", {{"min", {0.0, 1.0}}, {"max", {1.0, 2.0}}}}};
  data.config["sampler"] = {{"shift", 1.5}};
  data.config["actions"] = ranges;
  save_checkpoint(tmp / "trained", data);

  const auto trained = WorldModel::load(tmp / "trained", tmp / "tok");
  EXPECT_EQ(trained.trained_sampler().shift, 1.5);
  EXPECT_EQ(trained.action_ranges(), ranges);
  const auto plain = WorldModel::load(tmp / "plain", tmp / "tok");
  EXPECT_EQ(plain.trained_sampler().shift, SamplerOptions{}.shift);
  EXPECT_TRUE(plain.action_ranges().empty());

  data.config["sampler"] = {{"shift", -1}};
  save_checkpoint(tmp / "bad", data);
  EXPECT_THROW(WorldModel::load(tmp / "bad", tmp / "tok"), Error);
}

// The teacher as a step-by-step generator (policy evaluation, the server): a chunk per step from
// the last frame, with the trained sampler or fewer steps when asked.
TEST(WorldModel, TeacherGeneratorSamplesWithTheStepsAsked) {
  test::OneThread one;
  auto model = random_model();
  const auto first = torch::randint(0, 255, {16, 16, 3}, torch::kByte);
  const auto actions = torch::rand({12, 384}) * 2 - 1;
  SamplerOptions two = model.trained_sampler();
  two.steps = 2;
  const auto direct = model.predict_chunk(model.reconstruct_frames(first.unsqueeze(0)), actions.unsqueeze(0),
                                          /*seed=*/5, two);  // [1, 13, H, W, 3]
  auto fast = make_teacher_generator(model, nullptr, /*sampler_steps=*/2);
  EXPECT_EQ(fast->actions_per_step(), 12);
  fast->reset(first, 5);
  const auto frames = fast->step(actions);  // [12, H, W, 3]
  EXPECT_TRUE(frames.equal(direct[0].narrow(0, 1, 12)));
  auto trained = make_teacher_generator(model);  // 35 steps
  trained->reset(first, 5);
  EXPECT_FALSE(trained->step(actions).equal(frames));
  EXPECT_THROW(make_teacher_generator(model, nullptr, -1), Error);
}

}  // namespace dojo::infer

namespace dojo::infer {
namespace {

// --text-context: a zero embedding is the default; another one changes the prediction; a file of
// the wrong width is refused naming it.
TEST(WorldModel, TextContextFromAFile) {
  test::OneThread one;
  test::TempDir tmp;
  auto model = random_model();
  const int64_t channels = train::test_fixtures::tiny_dit(true, 32).crossattn_emb_channels;
  const auto first = torch::randint(0, 255, {1, 16, 16, 3}, torch::kByte);
  const auto actions = torch::rand({1, 12, 384});
  SamplerOptions s;
  s.steps = 2;
  const auto plain = model.predict_chunk(first, actions, 3, s);
  save_safetensors(tmp / "zeros.safetensors", {{"context", torch::zeros({1, channels})}});
  model.set_text_context(load_text_context(tmp / "zeros.safetensors"));
  EXPECT_TRUE(model.predict_chunk(first, actions, 3, s).equal(plain));
  torch::manual_seed(5);
  save_safetensors(tmp / "prompt.safetensors", {{"context", torch::randn({7, channels}) * 3}});
  model.set_text_context(load_text_context(tmp / "prompt.safetensors"));
  EXPECT_FALSE(model.predict_chunk(first, actions, 3, s).equal(plain));

  save_safetensors(tmp / "wide.safetensors", {{"context", torch::zeros({4, channels + 1})}});
  const std::string message = test::error_message([&] {
    model.set_text_context(load_text_context(tmp / "wide.safetensors"), (tmp / "wide.safetensors").string());
  });
  EXPECT_NE(message.find("wide.safetensors"), std::string::npos) << message;
  save_safetensors(tmp / "unnamed.safetensors", {{"prompt", torch::zeros({4, channels})}});
  EXPECT_NE(test::error_message([&] {
              load_text_context(tmp / "unnamed.safetensors");
            }).find("no tensor 'context'"),
            std::string::npos);
  // A torch.save file holding the tensor alone, as the released empty-prompt asset.
  const auto asset = load_text_context(test::torch_files_dir() / "prompt_embedding.pt");
  EXPECT_TRUE(asset.equal(torch::arange(12.0).reshape({1, 3, 4}).to(torch::kFloat32)));
}

}  // namespace
}  // namespace dojo::infer
