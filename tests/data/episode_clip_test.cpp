// Rollout clips from a LeRobot GR-1 set in raw units: the released frame stride, the normalisation
// the user chose (the model's range or the dataset's statistics), raw commands turned into the same
// rows the clip holds, and one-line errors for a robot nobody named.
#include "data/episode_clip.h"
#include "data/embodiments.h"

#include <torch/torch.h>

#include <nlohmann/json.hpp>

#include "lerobot_writer.h"
#include "test_util.h"

namespace dojo::data {
namespace {

using namespace lerobot_fixture;

// A range for GR-1's 29 dimensions unlike the dataset's: [-1000, 1000] everywhere.
ActionRanges wide_gr1_range() {
  ArrayStats wide;
  wide.min.assign(29, -1000.f);
  wide.max.assign(29, 1000.f);
  wide.mean.assign(29, 0.f);
  wide.std.assign(29, 1.f);
  return {{"gr1", wide}};
}

TEST(RolloutData, Gr1AtItsReleasedStrideWithTheDatasetsStatistics) {
  test::TempDir tmp;
  const auto root = make_lerobot(tmp / "set");
  const RolloutData data(root, 1, {});
  EXPECT_EQ(data.stride(), 2);
  EXPECT_EQ(data.normalization(), "dataset");
  EXPECT_EQ(data.action_slot(), "gr1");
  EXPECT_NE(data.describe().find("slot gr1 (29 actions), dataset normalisation, frame stride 2"),
            std::string::npos)
      << data.describe();
  const auto clip = data.read(data.find("train", "episode_000001"));
  EXPECT_DOUBLE_EQ(clip.fps, kFps / 2);
  ASSERT_EQ(clip.video.sizes(), (std::vector<int64_t>{13, 32, 32, 3}));
  // Frames 2, 4, ..., 26 of episode 1 (global frame numbers 30 + 2 k).
  EXPECT_NEAR(test::mean_level(clip.video[0]), level(32), 1.5);
  EXPECT_NEAR(test::mean_level(clip.video[12]), level(56), 1.5);
  ASSERT_EQ(clip.actions.sizes(), (std::vector<int64_t>{12, 384}));
  // Raw left_arm.0 rises by 1 a frame, 2 a step; the dataset's range spans 100 + 29 = 129.
  const float step = 2.f / 129.f * 2.f;
  EXPECT_NEAR(clip.actions[0][0].item<float>(), step, 1e-5);                 // 1 step after the baseline
  EXPECT_NEAR(clip.actions[3][0].item<float>(), 4 * step, 1e-5);             // 4 steps: the chunk's last row
  EXPECT_NEAR(clip.actions[4][0].item<float>(), step, 1e-5);                 // the next chunk starts afresh
  EXPECT_EQ(clip.actions.slice(1, 29, 384).abs().max().item<float>(), 0.f);  // nothing outside the slot
  ASSERT_EQ(clip.raw_baseline.sizes(), (std::vector<int64_t>{29}));
  EXPECT_FLOAT_EQ(clip.raw_baseline[0].item<float>(), raw_action(1, 0, 0));

  // The same episode's raw commands (steps 1 .. 12 at stride 2) give back the clip's rows.
  const auto arrays = data.source().read_arrays(data.find("train", "episode_000001"));
  const auto raw = arrays.actions.index_select(0, torch::arange(2, 26, 2));  // [12, 29]
  EXPECT_TRUE(torch::allclose(data.raw_to_rows(raw, clip.raw_baseline), clip.actions, 1e-5, 1e-6));
  EXPECT_EQ(test::error_message([&] { data.raw_to_rows(raw.narrow(1, 0, 28), clip.raw_baseline); }),
            "raw actions for slot 'gr1' must be 12 K rows of 29 values");
}

TEST(RolloutData, TheModelsRangeOrTheDatasetsByChoice) {
  test::TempDir tmp;
  const auto root = make_lerobot(tmp / "set");
  const RolloutData dataset_norm(root, 1, {});
  const RolloutData model_norm(root, 1, wide_gr1_range());
  EXPECT_EQ(model_norm.normalization(), "model");
  const auto a = dataset_norm.read(0).actions, b = model_norm.read(0).actions;
  EXPECT_NEAR(b[0][0].item<float>(), 2.f / 2000.f * 2.f, 1e-6);  // 2 units over the model's 2000
  EXPECT_FALSE(torch::allclose(a, b));
  RolloutDataOptions options;
  options.normalization = ActionNormalization::kDataset;
  EXPECT_TRUE(torch::equal(RolloutData(root, 1, wide_gr1_range(), options).read(0).actions, a));
  options.normalization = ActionNormalization::kModel;
  EXPECT_EQ(test::error_message([&] { RolloutData(root, 1, {}, options); }),
            root.string() + ": the model records no action range for slot 'gr1' (use --action-norm dataset)");
  EXPECT_EQ(test::error_message([] { parse_action_normalization("minmax"); }),
            "unknown action normalisation 'minmax' (auto, model, dataset)");
  EXPECT_NE(test::error_message([] {
              parse_action_ranges({{"gr2", {{"min", {0}}, {"max", {1}}}}}, "m");
            }).find("gr2"),
            std::string::npos);
}

TEST(RolloutData, AnUnnamedRobotIsRefusedAndStrideAndSizeFollowTheOptions) {
  test::TempDir tmp;
  Fixture fx;
  fx.robot_type = "";
  const auto root = make_lerobot(tmp / "gr1_in_the_path", fx);
  EXPECT_EQ(test::error_message([&] { RolloutData(root, 1, {}); }),
            root.string() +
                ": a robot dataset whose actions fill no slot of the 384-d layout; name the robot with "
                "--embodiment (" +
                embodiment_names() +
                "; human / none for its video alone; a new robot: --embodiments FILE, docs/new_robot.md)");
  RolloutDataOptions options;
  options.open.embodiment = "gr1";
  options.frame_stride = 1;
  options.height = options.width = 16;
  const RolloutData data(root, 2, {}, options);
  EXPECT_EQ(data.stride(), 1);
  const auto clip = data.read(data.find("", ""));
  ASSERT_EQ(clip.video.sizes(), (std::vector<int64_t>{25, 16, 16, 3}));
  EXPECT_NEAR(test::mean_level(clip.video[24]), level(25), 1.5);
  // 25 frames at stride 2 need 51 steps: the 30-frame episodes are too short.
  options.frame_stride = 0;
  const RolloutData strided(root, 2, {}, options);
  EXPECT_TRUE(strided.episodes("train").empty());
  EXPECT_EQ(test::error_message([&] { strided.find("train", "episode_000000"); }),
            root.string() + ": episode episode_000000 is shorter than 25 frames at stride 2");
  options.open.embodiment = "human";
  const RolloutData video_only(root, 1, {}, options);
  EXPECT_EQ(video_only.normalization(), "none");
  EXPECT_FALSE(video_only.read(0).raw_baseline.defined());
}

}  // namespace
}  // namespace dojo::data
