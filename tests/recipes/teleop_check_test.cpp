// The teleoperation check on recordings whose right answer is known: DojoSim's own frames of the
// recorded commands (a perfect world model), a stream frozen at the start frame, and frames of the
// same holds driven the other way. Recordings are written in the layout `dojo serve` writes.
#ifdef DOJO_WITH_SIM

#include "recipes/teleop_check.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/error.h"
#include "data/episode_store.h"
#include "io/video.h"
#include "sim/episode.h"
#include "sim/generate.h"
#include "sim/renderer.h"
#include "sim/world.h"
#include "test_util.h"

namespace fs = std::filesystem;

namespace dojo::recipes {
namespace {

const fs::path kProbe = fs::path(DOJO_SOURCE_DIR) / "models" / "reference" / "probe";

struct Hold {
  int dim;
  double per_row;  // command change per row
  int rows;
};

// The session's commands: from the episode's first action, each hold in turn. [R, 6]
torch::Tensor commands(const torch::Tensor& baseline, const std::vector<Hold>& holds) {
  std::vector<torch::Tensor> rows;
  auto c = baseline.to(torch::kFloat32).clone();
  for (const auto& h : holds)
    for (int i = 0; i < h.rows; ++i) {
      c[h.dim] += h.per_row;
      rows.push_back(c.clone());
    }
  return torch::stack(rows);
}

// DojoSim's frames of `rows` from the episode's scene: [1 + R, H, W, 3].
torch::Tensor dojosim_frames(const nlohmann::json& scene, const torch::Tensor& rows) {
  sim::World world(sim::scene_from_json(scene));
  world.hold(sim::EpisodeSpec{}.settle_steps);
  sim::Renderer renderer;
  std::vector<torch::Tensor> frames;
  const auto grab = [&] {
    auto rgb = renderer.render(world);
    frames.push_back(
        torch::from_blob(rgb.data(), {world.spec().height, world.spec().width, 3}, torch::kUInt8).clone());
  };
  grab();
  const auto r = rows.to(torch::kFloat64).contiguous();
  for (int64_t i = 0; i < r.size(0); ++i) {
    world.step(std::vector<double>(r[i].data_ptr<double>(), r[i].data_ptr<double>() + r.size(1)));
    grab();
  }
  return torch::stack(frames);
}

// A recording as `dojo serve` writes it: session.json, video.mp4, actions.jsonl (4 rows a step).
void write_recording(const fs::path& dir, const fs::path& data, const std::string& episode,
                     const torch::Tensor& rows, const torch::Tensor& video, int first_step = 0) {
  fs::create_directories(dir);
  std::ofstream(dir / "session.json") << nlohmann::json{
      {"model", "student"},
      {"episode", episode},
      {"data", data.string()},
      {"fps", 10.0},
      {"first_step", first_step}}.dump();
  std::ofstream actions(dir / "actions.jsonl");
  for (int64_t s = 0; s < rows.size(0); s += 4) {
    nlohmann::json raw = nlohmann::json::array();
    for (int64_t r = s; r < std::min<int64_t>(s + 4, rows.size(0)); ++r)
      raw.push_back(std::vector<float>(rows[r].data_ptr<float>(), rows[r].data_ptr<float>() + rows.size(1)));
    actions << nlohmann::json{{"raw", raw}}.dump() << "\n";
  }
  io::VideoWriterOptions w;
  w.fps = 10;
  io::write_video((dir / "video.mp4").string(), video, w);
}

class TeleopCheckTest : public ::testing::Test {
 protected:
  void SetUp() override {
    sim::GenerateOptions g;
    g.episodes = 1;
    g.frames = 4;
    g.workers = 1;
    g.seed = 11;
    g.val_fraction = 0;
    sim::generate_dataset(tmp / "robot", g);
    const auto store = data::EpisodeStore::open(tmp / "robot");
    episode = store.info().episodes[0].id;
    const auto arrays = store.load_arrays(0);
    scene = arrays.meta["scene"];
    // Base yaw and shoulder each one way for a second, then back; then the gripper, which moves no
    // keypoint the replay can count. (The elbow is left out: in its bent poses the reference probe
    // misses the gripper on DojoSim's own frames, so a perfect stream would not score perfectly.)
    rows = commands(arrays.actions[0], {{0, 0.03, 10},
                                        {0, -0.03, 10},
                                        {1, 0.05, 10},
                                        {1, -0.05, 10},
                                        {5, -0.05, 10},
                                        {5, 0.05, 10}});  // [60, 6]
    // The same holds the other way: every command mirrored about the episode's first action.
    mirrored = 2 * arrays.actions[0].to(torch::kFloat32).view({1, -1}) - rows;
  }
  TeleopCheck check(const fs::path& recording) {
    TeleopCheckOptions o;
    o.recording = recording;
    o.probe = kProbe;
    return check_teleop_recording(o);
  }
  test::TempDir tmp;
  std::string episode;
  nlohmann::json scene;
  torch::Tensor rows, mirrored;
};

TEST_F(TeleopCheckTest, DojoSimsOwnFramesFollowEveryKeyAndKeepTheArm) {
  write_recording(tmp / "perfect", tmp / "robot", episode, rows, dojosim_frames(scene, rows));
  const auto r = check(tmp / "perfect");
  SCOPED_TRACE(r.to_json().dump());
  EXPECT_EQ(r.frames, 61);
  ASSERT_EQ(r.keys.size(), 6u);
  EXPECT_EQ(r.keys[0].dimension, "base_yaw");
  EXPECT_EQ(r.keys[0].sign, 1);
  EXPECT_EQ(r.keys[3].sign, -1);
  EXPECT_EQ(r.keys[4].dimension, "gripper");
  EXPECT_FALSE(r.keys[4].counted);
  EXPECT_EQ(r.counted_keys, 4);
  EXPECT_EQ(r.sign_agreement, 1.0);
  EXPECT_GE(r.arm_found_where_in_view, 0.9);
  EXPECT_NEAR(r.arm_found_in_replay, r.arm_found_where_in_view, 0.05);  // the same frames, up to the mp4
  EXPECT_LT(r.keypoint_error_px, 3.0);
  EXPECT_GT(r.detected, 0.5);
  EXPECT_GE(r.scene_kept, 0.98);
  EXPECT_NEAR(r.arm_found, r.arm_found_by_probe_alone, 0.02);  // (almost) nothing gated away
  ASSERT_EQ(r.scene_share.size(), 61u);
}

// A stream that dissolves into horizontal bands of the arm's dark grey across the scene (how a
// drifting student ends): the probe may still read an arm into the bands; the scene check keeps
// none of those frames.
TEST_F(TeleopCheckTest, AStreamDissolvedIntoBandsKeepsNoSceneAndNoArm) {
  auto frames = dojosim_frames(scene, rows).clone();  // [61, H, W, 3]
  const int64_t kept = 11;
  for (int64_t t = kept; t < frames.size(0); ++t)
    for (int64_t y = 0; y < frames.size(1); y += 8) frames[t].narrow(0, y, 4).fill_(55);
  write_recording(tmp / "bands", tmp / "robot", episode, rows, frames);
  const auto r = check(tmp / "bands");
  SCOPED_TRACE(r.to_json().dump());
  EXPECT_NEAR(r.scene_kept, static_cast<double>(kept) / 61, 0.02);
  EXPECT_EQ(r.scene_kept_last_100, r.scene_kept);  // 61 frames: the last 100 are all of them
  EXPECT_LE(r.arm_found, static_cast<double>(kept) / 61 + 1e-9);
  EXPECT_GT(r.scene_share[0], 0.95);
  EXPECT_LT(r.scene_share[40], 0.6);
  // No hold that ends in the bands agrees, whatever the probe reads into them.
  ASSERT_EQ(r.counted_keys, 4);
  for (const auto& k : r.keys) {
    if (k.first_row + k.rows >= kept) {
      EXPECT_FALSE(k.agrees || k.stream_found) << k.dimension;
    }
  }
}

TEST_F(TeleopCheckTest, AFrozenStreamAndAStreamDrivenTheOtherWayDisagree) {
  const auto perfect = dojosim_frames(scene, rows);
  write_recording(tmp / "frozen", tmp / "robot", episode, rows,
                  perfect.narrow(0, 0, 1).expand({rows.size(0) + 1, -1, -1, -1}).contiguous());
  const auto frozen = check(tmp / "frozen");
  SCOPED_TRACE(frozen.to_json().dump());
  ASSERT_EQ(frozen.counted_keys, 4);
  EXPECT_EQ(frozen.sign_agreement, 0.0);
  for (const auto& k : frozen.keys) EXPECT_LT(std::hypot(k.stream_motion[0], k.stream_motion[1]), 1.0);

  write_recording(tmp / "mirrored", tmp / "robot", episode, rows, dojosim_frames(scene, mirrored));
  const auto wrong_way = check(tmp / "mirrored");
  SCOPED_TRACE(wrong_way.to_json().dump());
  ASSERT_EQ(wrong_way.counted_keys, 4);
  EXPECT_EQ(wrong_way.sign_agreement, 0.0);
  EXPECT_GE(wrong_way.arm_found_where_in_view, 0.9);  // the arm is there; it moves the wrong way
}

TEST_F(TeleopCheckTest, RecordingsThatCannotBeReplayedAreRefused) {
  const auto frames = dojosim_frames(scene, rows);
  write_recording(tmp / "late", tmp / "robot", episode, rows, frames, /*first_step=*/3);
  EXPECT_NE(test::error_message([&] { check(tmp / "late"); }).find("first_step 3"), std::string::npos);
  write_recording(tmp / "short", tmp / "robot", episode, rows, frames.narrow(0, 0, 40));
  EXPECT_NE(test::error_message([&] { check(tmp / "short"); }).find("40 frames, but actions.jsonl has 60"),
            std::string::npos);
  write_recording(tmp / "other", tmp / "robot", "999999", rows, frames);
  EXPECT_NE(test::error_message([&] { check(tmp / "other"); }).find("no episode '999999'"),
            std::string::npos);
}

TEST(UnchangedSceneShare, ScoresOnlyWhatTheReplayLeavesUnchanged) {
  // A grey scene with a bright square that moves: the square's old and new pixels are not scored.
  auto replay = torch::full({3, 16, 16, 3}, 100, torch::kUInt8);
  replay[0].narrow(0, 2, 4).narrow(1, 2, 4).fill_(250);
  replay[1].narrow(0, 8, 4).narrow(1, 8, 4).fill_(250);
  replay[2].narrow(0, 8, 4).narrow(1, 8, 4).fill_(250);
  auto stream = replay.clone();
  stream[1].narrow(0, 8, 4).narrow(1, 8, 4).fill_(0);  // the moving part wrong: not scored
  stream[2].narrow(0, 0, 2).fill_(160);                // 32 unchanged pixels off by 60: scored
  stream[2].narrow(0, 14, 2).fill_(120);               // 32 more off by 20: within the tolerance
  const auto share = recipes::unchanged_scene_share(stream, replay);
  EXPECT_EQ(share[0].item<double>(), 1.0);
  EXPECT_EQ(share[1].item<double>(), 1.0);
  EXPECT_NEAR(share[2].item<double>(), 1.0 - 32.0 / 224, 1e-12);  // 224 unchanged pixels
  EXPECT_THROW(recipes::unchanged_scene_share(stream.narrow(0, 0, 2), replay), Error);
}

}  // namespace
}  // namespace dojo::recipes

#endif  // DOJO_WITH_SIM
