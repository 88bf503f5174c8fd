#include "eval/wm_eval.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cmath>

#include "eval/metrics.h"
#include "io/video.h"
#include "synthetic_data.h"
#include "test_util.h"
#include "train/wm_test_fixtures.h"

namespace dojo::eval {
namespace {

// A random world model and probe on synthetic episodes: every source is scored, the copy-frame
// baseline is exact, the probe's keypoint scores and the action-sensitivity runs appear, and the
// side-by-side video is enlarged.
TEST(WmEval, ScoresEverySourceWithKeypointsAndActionSensitivity) {
  test::OneThread one;
  test::TempDir tmp;
  test::SyntheticOptions data;
  data.episodes = 3;
  data.frames = 30;
  data.size = 16;
  test::write_synthetic_dataset(tmp / "robot", data);
  torch::manual_seed(0);
  infer::WorldModel model(models::ActionDit(train::test_fixtures::tiny_dit(true, 32)),
                          models::WanVae(models::WanVaeConfig::tiny()));
  models::KeypointProbeConfig pc;
  pc.size = 16;
  pc.width = 8;
  pc.keypoints = {"arm.a", "arm.b", "arm.c"};
  models::KeypointProbe probe(pc);

  WmEvalOptions o;
  o.chunks = 2;
  o.sampler.steps = 2;
  o.probe = &probe;
  o.action_sensitivity = true;
  o.video_dir = tmp / "videos";
  o.videos = 1;
  o.video_scale = 3;
  o.batch = 1;  // each episode rolled out alone, so a rollout made here below draws the same noise
  const auto r = evaluate_world_model(model, tmp / "robot", "all", o);
  ASSERT_EQ(r.videos.size(), 3u);
  for (const char* name :
       {"world_model", "copy_frame", "tokenizer", "shuffled_actions", "zero_actions", "ground_truth"})
    ASSERT_TRUE(r.sources.count(name)) << name;
  EXPECT_EQ(r.frames, 25);
  EXPECT_EQ(r.model().psnr_per_frame.size(), 25u);
  EXPECT_EQ(r.copy_frame().psnr_per_frame[0], 80.0);  // frame 0 is the real frame itself
  // Scores are on the predicted frames: copy-frame's free 80 dB at frame 0 only in the released
  // protocol's number.
  auto mean_from = [](const std::vector<double>& v, size_t first) {
    double sum = 0;
    for (size_t i = first; i < v.size(); ++i) sum += v[i];
    return sum / static_cast<double>(v.size() - first);
  };
  const auto& copy_curve = r.copy_frame().psnr_per_frame;
  EXPECT_NEAR(r.copy_frame().psnr, mean_from(copy_curve, 1), 1e-9);
  EXPECT_NEAR(r.copy_frame().psnr_all_frames, mean_from(copy_curve, 0), 1e-9);
  EXPECT_LT(r.copy_frame().psnr, r.copy_frame().psnr_all_frames);
  EXPECT_NEAR(r.model().keypoint_error, mean_from(r.model().keypoint_error_per_frame, 1), 1e-9);
  EXPECT_FALSE(std::isnan(r.model().keypoint_error));
  EXPECT_FALSE(std::isnan(r.sources.at("ground_truth").detection));
  EXPECT_EQ(r.model().keypoint_error_per_frame.size(), 25u);
  EXPECT_EQ(r.tokenizer_psnr_by_latent.size(), 4u);
  // The action-sensitivity runs are what they say: episode i's "shuffled" rollout is its first
  // frame driven by episode i+1's actions, its "zero" rollout the same frame with zero actions, and
  // both differ from the true-action rollout.
  const auto& shuffled = r.sources.at("shuffled_actions");
  const auto& zero = r.sources.at("zero_actions");
  EXPECT_NE(r.model().psnr, shuffled.psnr);
  EXPECT_NE(r.model().psnr, zero.psnr);
  for (size_t i = 0; i < r.videos.size(); ++i) {
    const auto ranges = data::parse_action_ranges(model.action_ranges(), "model");
    const auto clip = data::read_episode_clip(tmp / "robot", "all", r.videos[i].episode, o.chunks, ranges);
    const auto next = data::read_episode_clip(tmp / "robot", "all",
                                              r.videos[(i + 1) % r.videos.size()].episode, o.chunks, ranges);
    const auto first = clip.video.select(0, 0).unsqueeze(0);
    const auto gt = clip.video.unsqueeze(0);
    auto psnr_of = [&](const torch::Tensor& actions) {
      const auto video = model.rollout(first, actions.unsqueeze(0), o.seed, o.sampler, o.concat);
      return psnr_per_frame(video[0], gt[0]).narrow(0, 1, gt.size(1) - 1).mean().item<double>();
    };
    EXPECT_NEAR(r.videos[i].sources.at("world_model").psnr, psnr_of(clip.actions), 1e-4) << i;
    EXPECT_NEAR(r.videos[i].sources.at("shuffled_actions").psnr, psnr_of(next.actions), 1e-4) << i;
    EXPECT_NEAR(r.videos[i].sources.at("zero_actions").psnr, psnr_of(torch::zeros_like(clip.actions)), 1e-4)
        << i;
  }

  const auto j = r.to_json();
  EXPECT_TRUE(j.contains("world_model") && j["world_model"].contains("keypoint_error_px"));
  EXPECT_EQ(j["per_frame"]["copy_frame"]["psnr"].size(), 25u);
  const auto table = markdown_table({r});
  EXPECT_NE(table.find("Keypoint error"), std::string::npos) << table;
  EXPECT_NE(table.find("Action sensitivity"), std::string::npos) << table;

  ASSERT_FALSE(r.videos[0].video.empty());
  const auto info = io::probe_video(r.videos[0].video);
  EXPECT_GE(info.width, 4 * 16 * 3);  // four panels, each 3x the frame
  EXPECT_GE(info.height, 16 * 3);

  o.max_episodes = 1;
  EXPECT_NE(
      test::error_message([&] { evaluate_world_model(model, tmp / "robot", "all", o); }).find("at least 2"),
      std::string::npos);
}

}  // namespace
}  // namespace dojo::eval
