#include "train/distill.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "core/error.h"
#include "diffusion/samplers.h"
#include "test_util.h"
#include "wm_test_fixtures.h"

namespace dojo::train {
namespace {

using test::TempDir;
using test_fixtures::gen;

LatentClips action_clips(int64_t n, uint64_t seed) {
  LatentClips clips;
  test_fixtures::action_driven_latents(n, clips.latents, clips.actions, seed);  // [n, 16, 4, 4, 4]
  return clips;
}

TEST(Distill, WeightedWarmupDrawsEachDatasetsShareOverEveryCopy) {
  // Datasets of 30 and 10 clips weighted 1:3, 2 copies per clip (trajectory j = clip j % 40 under
  // copy j / 40): the small dataset fills three quarters of the draws, both copies alike.
  const MixtureIndex mixture({30, 10}, {1, 3});
  auto gen = step_generator(11, 0);
  const auto idx = draw_trajectories(mixture, 2, 20000, gen);
  ASSERT_TRUE(idx.min().item<int64_t>() >= 0 && idx.max().item<int64_t>() < 80);
  const auto clip = idx.remainder(40), copy = idx.div(40, "floor");
  EXPECT_NEAR(clip.ge(30).to(torch::kDouble).mean().item<double>(), 0.75, 0.01);
  EXPECT_NEAR(copy.eq(1).to(torch::kDouble).mean().item<double>(), 0.5, 0.01);
  // Unweighted: the stream the warm-up drew before weights existed.
  const MixtureIndex alike({30, 10});
  auto a = step_generator(4, 3), b = step_generator(4, 3);
  EXPECT_TRUE(torch::equal(draw_trajectories(alike, 2, 16, a), torch::randint(80, {16}, b, torch::kLong)));
}

TEST(Distill, CleanContextRowsAreCleanBeforeAFrontierAndDrawnAsBeforeAfterIt) {
  const int64_t B = 4000, T = 13, P = 5;
  auto a = step_generator(3, 1), b = step_generator(3, 1);
  const auto drawn = torch::randint(P, {B, T}, a, torch::kLong);
  // Share 0 draws nothing: the warm-up's stream of draws is the one it had before the option.
  EXPECT_TRUE(torch::equal(with_clean_context(drawn, 0, P, a), drawn));
  torch::randint(P, {B, T}, b, torch::kLong);  // b where a was before with_clean_context
  EXPECT_TRUE(
      torch::equal(torch::randint(P, {B, T}, a, torch::kLong), torch::randint(P, {B, T}, b, torch::kLong)));

  auto g = step_generator(5, 2);
  const auto out = with_clean_context(drawn, 0.5, P, g);
  int64_t changed_rows = 0;
  std::vector<int64_t> frontier_count(T, 0);
  for (int64_t r = 0; r < B; ++r) {
    const auto row = out[r], orig = drawn[r];
    if (torch::equal(row, orig) && orig[0].item<int64_t>() != P - 1) continue;  // not chosen
    // A chosen row: a clean prefix of length k >= 1, then the drawn points unchanged.
    int64_t k = 0;
    while (k < T && row[k].item<int64_t>() == P - 1) ++k;
    ASSERT_GE(k, 1);
    EXPECT_TRUE(torch::equal(row.narrow(0, k, T - k), orig.narrow(0, k, T - k)));
    // k may run past the frontier where the drawn points were already clean; count the changed.
    if (!torch::equal(row, orig)) ++changed_rows;
  }
  // About half the rows chosen; a chosen row is changed unless its prefix was already clean.
  EXPECT_GT(changed_rows, B * 0.44);
  EXPECT_LT(changed_rows, B * 0.52);
  EXPECT_THROW(with_clean_context(drawn, 1.5, P, g), Error);
}

TEST(Distill, ContextNoiseLandsOnTheCleanFramesAfterTheFirstOnly) {
  const int64_t B = 64, T = 13, P = 5;
  auto g = step_generator(7, 1);
  const auto index = torch::randint(P, {B, T}, g, torch::kLong);
  auto none = step_generator(7, 2);
  EXPECT_FALSE(context_noise_offsets(index, P, {16, 4, 4}, 0, none).defined());
  auto h = step_generator(7, 2);
  const auto offset = context_noise_offsets(index, P, {16, 4, 4}, 0.5, h);  // [B, 16, T, 4, 4]
  ASSERT_EQ(offset.sizes(), (std::vector<int64_t>{B, 16, T, 4, 4}));
  const auto touched = offset.abs().amax({1, 3, 4}).gt(0);  // [B, T]
  auto expected = index.eq(P - 1);
  expected.select(1, 0).fill_(false);
  EXPECT_TRUE(torch::equal(touched, expected));
  EXPECT_GT(expected.sum().item<int64_t>(), B);  // the draw put clean frames in most rows
  // One level a clip, below the maximum: the noise's spread per clip stays under 0.5.
  const auto per_clip =
      (offset.pow(2).sum({1, 2, 3, 4}) / (expected.sum(1).to(torch::kFloat32) * 16 * 4 * 4).clamp_min(1))
          .sqrt();  // [B]
  EXPECT_LT(per_clip.max().item<double>(), 0.5 * 1.2);
  EXPECT_GT(per_clip.max().item<double>(), 0.25);
}

TEST(Distill, TrajectoriesAreTheTeachersOdePointsPerClipAndResume) {
  test::OneThread one;
  torch::manual_seed(0);
  models::ActionDit teacher(test_fixtures::tiny_dit(/*live_actions=*/true));
  teacher->eval();
  const auto clips = action_clips(5, 1);
  TempDir dir;
  TrajectorySpec spec;
  spec.teacher_steps = 6;
  spec.query_steps = {0, 2, 4};
  spec.shard_clips = 2;
  spec.batch = 2;
  const nlohmann::json fp = {{"teacher", "a"}};
  const auto t = load_or_build_trajectories(*teacher, 5.0, clips, spec, fp, dir.path());
  ASSERT_EQ(t.points.sizes(), (std::vector<int64_t>{5, 4, 16, 4, 4, 4}));
  const auto schedule = diffusion::flow_sigma_schedule(6, 5.0);
  EXPECT_EQ(t.timesteps,
            (std::vector<int64_t>{schedule.timesteps[0], schedule.timesteps[2], schedule.timesteps[4], 0}));
  // Frame 0 of every point is the clip's clean conditioning latent.
  for (int64_t p = 0; p < 4; ++p)
    EXPECT_TRUE(t.points.select(1, p).select(2, 0).equal(clips.latents.select(2, 0)));
  // Point 0 is the clip's own noise (frames >= 1), so batching does not change the draws.
  spec.batch = 1;
  TempDir other;
  const auto one_by_one = load_or_build_trajectories(*teacher, 5.0, clips, spec, fp, other.path());
  EXPECT_LT((one_by_one.points - t.points).abs().max().item<double>(), 1e-5);
  // The points move along the ODE: each differs from the one before on the predicted frames.
  for (int64_t p = 1; p < 4; ++p)
    EXPECT_GT((t.points.select(1, p) - t.points.select(1, p - 1)).narrow(2, 1, 3).abs().max().item<double>(),
              1e-3);

  // A second call reads the shards; another teacher rebuilds them.
  const auto shard = dir / "shard-00000.safetensors";
  const auto written = std::filesystem::last_write_time(shard);
  const auto again = load_or_build_trajectories(*teacher, 5.0, clips, spec, fp, dir.path());
  EXPECT_TRUE(again.points.equal(t.points));
  EXPECT_EQ(std::filesystem::last_write_time(shard), written);
  load_or_build_trajectories(*teacher, 5.0, clips, spec, {{"teacher", "b"}}, dir.path());
  EXPECT_NE(std::filesystem::last_write_time(shard), written);
}

// Counterfactual copies: each clip's first frame and noise again, with another clip's actions. The
// copy is exactly the trajectory of a clip set whose actions were swapped, and it differs from the
// clip's own, so the warm-up's target depends on the actions.
TEST(Distill, CounterfactualTrajectoriesPairEachFirstFrameWithOtherActions) {
  test::OneThread one;
  torch::manual_seed(0);
  models::ActionDit teacher(test_fixtures::tiny_dit(/*live_actions=*/true));
  teacher->eval();
  const auto clips = action_clips(4, 3);
  TrajectorySpec spec;
  spec.teacher_steps = 6;
  spec.query_steps = {0, 2, 4};
  spec.counterfactual_copies = 1;
  TempDir dir;
  const auto t = load_or_build_trajectories(*teacher, 5.0, clips, spec, {}, dir.path());
  ASSERT_EQ(t.size(), 8);
  EXPECT_TRUE(t.actions.narrow(0, 0, 4).equal(clips.actions));  // the clips' own first
  // Copy k = 1 of clip i carries clip (i + stride) % 4's actions, stride = 4 / 2 / 2 + 1 = 2.
  LatentClips swapped = clips;
  swapped.actions = clips.actions.index_select(0, torch::tensor({2, 3, 0, 1}, torch::kLong));
  EXPECT_TRUE(t.actions.narrow(0, 4, 4).equal(swapped.actions));
  spec.counterfactual_copies = 0;
  TempDir plain;
  const auto direct = load_or_build_trajectories(*teacher, 5.0, swapped, spec, {}, plain.path());
  EXPECT_LT((t.points.narrow(0, 4, 4) - direct.points).abs().max().item<double>(), 1e-5);
  // Same first frame, same noise (point 0), other actions: another x0.
  EXPECT_TRUE(t.points.narrow(0, 4, 4).select(1, 0).equal(t.points.narrow(0, 0, 4).select(1, 0)));
  const auto last = t.points.size(1) - 1;
  EXPECT_GT((t.points.narrow(0, 4, 4).select(1, last) - t.points.narrow(0, 0, 4).select(1, last))
                .narrow(2, 1, 3)
                .abs()
                .max()
                .item<double>(),
            1e-3);
}

// Chained chunks: chunk 0 is the one-chunk trajectory of the clip; chunk 1 is the teacher's
// trajectory from chunk 0's final last latent with the next 12 actions and its own noise.
// 7 latents (25 frames) and 24 actions from 4-latent clips: the second chunk's actions are the
// clips' own in reverse clip order. Only the first latent and the actions are read.
LatentClips two_chunk_clips(const LatentClips& short_clips) {
  LatentClips clips;
  clips.latents = torch::cat({short_clips.latents, torch::randn({3, 16, 3, 4, 4}, gen(9))}, 2);
  clips.actions = torch::cat({short_clips.actions, short_clips.actions.flip(0)}, 1);
  return clips;
}

// Two teacher chunks of 6 steps, the points before steps 0, 2 and 4.
TrajectorySpec two_chunk_spec() {
  TrajectorySpec spec;
  spec.teacher_steps = 6;
  spec.query_steps = {0, 2, 4};
  spec.chunks = 2;
  return spec;
}

TEST(Distill, ChainedTrajectoriesRollTheTeacherOutChunkByChunk) {
  test::OneThread one;
  torch::manual_seed(0);
  models::ActionDit teacher(test_fixtures::tiny_dit(/*live_actions=*/true));
  teacher->eval();
  const auto short_clips = action_clips(3, 4);
  const auto clips = two_chunk_clips(short_clips);
  auto spec = two_chunk_spec();
  TempDir dir;
  const auto t = load_or_build_trajectories(*teacher, 5.0, clips, spec, {}, dir.path());
  ASSERT_EQ(t.points.sizes(), (std::vector<int64_t>{3, 4, 16, 7, 4, 4}));
  EXPECT_TRUE(t.actions.equal(clips.actions));
  spec.chunks = 1;
  TempDir one_chunk;
  const auto first = load_or_build_trajectories(*teacher, 5.0, short_clips, spec, {}, one_chunk.path());
  EXPECT_LT((t.points.narrow(3, 0, 4) - first.points).abs().max().item<double>(), 1e-5);
  LatentClips next;
  next.latents = short_clips.latents.clone();
  next.latents.narrow(2, 0, 1).copy_(t.points.select(1, 3).narrow(2, 3, 1));  // chunk 0's last x0
  next.actions = short_clips.actions.flip(0);
  spec.seed += 1000003;  // chunk 1's noise
  TempDir second_chunk;
  const auto second = load_or_build_trajectories(*teacher, 5.0, next, spec, {}, second_chunk.path());
  EXPECT_LT((t.points.narrow(3, 4, 3) - second.points.narrow(3, 1, 3)).abs().max().item<double>(), 1e-5);
  // A clip too short for the chunks asked is refused.
  spec.chunks = 3;
  EXPECT_THROW(load_or_build_trajectories(*teacher, 5.0, clips, spec, {}, dir.path()), Error);
}

// With re-encoded anchors, chunk 1 starts where the teacher's own rollout would: chunk 0 decoded
// to uint8 frames, its last frame encoded alone, not chunk 0's last latent (frames 9-12).
TEST(Distill, ReencodedAnchorsStartEachChunkFromItsPredecessorsLastFrameEncodedAlone) {
  test::OneThread one;
  torch::manual_seed(0);
  models::ActionDit teacher(test_fixtures::tiny_dit(/*live_actions=*/true));
  teacher->eval();
  models::WanVae tokenizer(models::WanVaeConfig::tiny());  // 32x32 frames <-> [16, T, 4, 4] latents
  tokenizer->eval();
  const auto short_clips = action_clips(3, 4);
  const auto clips = two_chunk_clips(short_clips);
  auto spec = two_chunk_spec();
  spec.reencode_anchor = true;
  TempDir dir;
  EXPECT_THROW(load_or_build_trajectories(*teacher, 5.0, clips, spec, {}, dir.path()),
               Error);  // no tokenizer
  const auto t = load_or_build_trajectories(*teacher, 5.0, clips, spec, {}, dir.path(), tokenizer.get());
  ASSERT_EQ(t.points.sizes(), (std::vector<int64_t>{3, 4, 16, 7, 4, 4}));
  torch::Tensor anchor;
  {
    torch::NoGradGuard no_grad;
    const auto frames =
        models::model_to_video(tokenizer->decode_latents(t.points.select(1, 3).narrow(2, 0, 4)));
    anchor = tokenizer->encode_latents(models::video_to_model(frames.narrow(1, 12, 1)));  // [3, 16, 1, 4, 4]
  }
  EXPECT_GT((anchor - t.points.select(1, 3).narrow(2, 3, 1)).abs().max().item<double>(), 1e-3)
      << "the re-encoded frame is not the chunk's last latent";
  LatentClips next;
  next.latents = short_clips.latents.clone();
  next.latents.narrow(2, 0, 1).copy_(anchor);
  next.actions = short_clips.actions.flip(0);
  spec.seed += 1000003;  // chunk 1's noise
  spec.chunks = 1;
  TempDir second_chunk;
  const auto second = load_or_build_trajectories(*teacher, 5.0, next, spec, {}, second_chunk.path());
  EXPECT_LT((t.points.narrow(3, 4, 3) - second.points.narrow(3, 1, 3)).abs().max().item<double>(), 1e-5);
  // Latent anchors are another trajectory: the shards record the anchor and are rebuilt.
  spec.seed -= 1000003;
  spec.chunks = 2;
  spec.reencode_anchor = false;
  const auto latent = load_or_build_trajectories(*teacher, 5.0, clips, spec, {}, dir.path());
  EXPECT_GT((latent.points.narrow(3, 4, 3) - t.points.narrow(3, 4, 3)).abs().max().item<double>(), 1e-4);
}

TEST(Distill, WarmupRegressionLearnsTheTeachersX0) {
  test::OneThread one;
  torch::manual_seed(0);
  models::ActionDit teacher(test_fixtures::tiny_dit(/*live_actions=*/true));
  teacher->eval();
  const auto clips = action_clips(8, 2);
  TempDir dir;
  TrajectorySpec spec;
  spec.teacher_steps = 6;
  spec.query_steps = {0, 2, 4};
  const auto t = load_or_build_trajectories(*teacher, 5.0, clips, spec, {}, dir.path());

  WmTrainOptions o;
  o.lr = 1e-3;
  o.warmup_steps = 0;
  o.grad_clip = 1;
  models::ActionDit student(teacher->config);
  WmTrainer trainer(student, o);
  const auto fixed = [&] {
    torch::NoGradGuard no_grad;
    return warmup_loss(*trainer.net(), t.points, t.actions, t.timesteps, 2, gen(99)).item<double>();
  };
  const double before = fixed();
  for (int step = 0; step < 40; ++step) {
    auto g = gen(static_cast<uint64_t>(step));
    trainer.step_loss(
        [&](models::ActionDitImpl& net) { return warmup_loss(net, t.points, t.actions, t.timesteps, 2, g); });
  }
  const double after = fixed();
  std::printf("warm-up loss %.4f -> %.4f\n", before, after);
  EXPECT_LT(after, 0.5 * before);
}

}  // namespace
}  // namespace dojo::train
