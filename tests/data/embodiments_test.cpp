// The user's embodiment table: a robot the engine has not seen, named in a JSON file, read from a
// LeRobot dataset the exporter wrote; tables that would corrupt a released robot's columns refused.
#include "data/embodiments.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <fstream>

#include "data/episode_clip.h"
#include "data/episode_source.h"
#include "data/episode_store.h"
#include "data/lerobot_export.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo::data {
namespace {

// The synthetic robot's six named dimensions in the mano range, stride 2.
nlohmann::json arm_spec(const std::string& name, int begin = 240) {
  nlohmann::json action = nlohmann::json::array();
  for (const char* key : {"y", "x", "a", "b", "c", "d"}) action.push_back({key, 1});
  return {{"name", name},
          {"robot_types", {name + "_v2", "Crane-" + name}},
          {"slot", {begin, begin + 6}},
          {"action", action},
          {"camera", "front"},
          {"frame_stride", 2}};
}

std::filesystem::path write_table(const std::filesystem::path& file,
                                  const std::vector<nlohmann::json>& entries) {
  nlohmann::json table = nlohmann::json::object();
  table["embodiments"] = entries;
  std::ofstream(file) << table.dump(2);
  return file;
}

TEST(Embodiments, ARobotOfTheTableReadsFromAnExportedLeRobotSet) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 3;
  g.val_episodes = 1;
  g.frames = 30;
  test::write_synthetic_dataset(tmp / "sim", g);
  load_embodiment_table(write_table(tmp / "robots.json", {arm_spec("crane_arm")}));
  EXPECT_EQ(slot_by_name("crane_arm").begin, 240);
  EXPECT_EQ(detect_robot("CRANE-crane_arm"), "crane_arm") << "robot_types match in any case";
  EXPECT_EQ(released_frame_stride("crane_arm"), 2);
  EXPECT_NE(embodiment_names().find("crane_arm"), std::string::npos);
  const auto table = embodiment_table().at("embodiments");
  EXPECT_EQ(table.back().at("name"), "crane_arm");
  EXPECT_EQ(table.front().at("name"), "gr1");
  EXPECT_EQ(table.front().at("frame_stride"), 2);

  const auto source = open_dataset(tmp / "sim");
  LeRobotExportOptions options;
  options.robot_type = "crane_arm_v2";
  const auto result = export_lerobot(*source, tmp / "lerobot", options);
  EXPECT_EQ(result.converted, 3);
  // A rerun keeps what is there; other options are refused.
  EXPECT_EQ(export_lerobot(*source, tmp / "lerobot", options).kept, 3);
  options.crf = 30;
  EXPECT_NE(
      test::error_message([&] { export_lerobot(*source, tmp / "lerobot", options); }).find("other options"),
      std::string::npos);

  const auto lerobot = open_dataset(tmp / "lerobot");  // robot_type names the robot of the table
  const auto& info = lerobot->info();
  EXPECT_EQ(lerobot->format(), "lerobot-v2.1");
  EXPECT_EQ(info.action_slot, "crane_arm");
  EXPECT_EQ(info.action_dim, 6);
  ASSERT_EQ(info.episodes.size(), 3u);
  EXPECT_EQ(info.split_counts().at("val"), 1);
  EXPECT_EQ(info.episodes.back().split, "val") << "episodes are numbered split by split";
  ASSERT_TRUE(info.action_stats.has_value());
  for (size_t i = 0; i < 3; ++i) {
    const auto exported = lerobot->read_arrays(i).actions, original = source->read_arrays(i).actions;
    EXPECT_TRUE(torch::allclose(exported, original, 0, 1e-6)) << "episode " << i << ": raw, in slot order";
  }
  const auto frames = lerobot->read_frames(0, {0, 5}).to(torch::kFloat32),
             original = source->read_frames(0, {0, 5}).to(torch::kFloat32);
  EXPECT_LT((frames - original).abs().mean().item<double>(), 6.0) << "H.264 at crf 18";

  // Rollouts read it in the robot's slot at its stride.
  RolloutDataOptions rollout;
  rollout.open.embodiment = "crane_arm";
  const RolloutData data(tmp / "lerobot", 1, {}, rollout);
  EXPECT_EQ(data.action_slot(), "crane_arm");
  EXPECT_EQ(data.stride(), 2);
}

TEST(Embodiments, TablesThatWouldTakeAnotherRobotsColumnsAreRefused) {
  test::TempDir tmp;
  const auto refused = [&](nlohmann::json spec) {
    return test::error_message([&] { load_embodiment_table(write_table(tmp / "bad.json", {spec})); });
  };
  auto spec = arm_spec("bolt_arm", 230);  // beside the other test's robot, should both run in one process
  spec["slot"] = {20, 26};
  EXPECT_NE(refused(spec).find("overlaps 'gr1' [0, 29)"), std::string::npos) << refused(spec);
  spec["slot"] = {350, 356};
  EXPECT_NE(refused(spec).find("must lie in [0, 352)"), std::string::npos) << refused(spec);
  spec["slot"] = {230, 237};
  EXPECT_NE(refused(spec).find("widths add up to 6, the slot holds 7"), std::string::npos) << refused(spec);
  spec = arm_spec("gr1");
  EXPECT_NE(refused(spec).find("built-in embodiment"), std::string::npos) << refused(spec);
  spec = arm_spec("bolt_arm", 230);
  spec.erase("slot");
  EXPECT_NE(refused(spec).find("bad.json: embodiments[0] (bolt_arm).slot: missing"), std::string::npos)
      << refused(spec);
  EXPECT_EQ(find_user_embodiment("bolt_arm"), nullptr) << "nothing registered from a refused entry";

  // Two robots may not share columns; the same entry twice is one robot.
  load_embodiment_table(write_table(tmp / "one.json", {arm_spec("bolt_arm", 230)}));
  load_embodiment_table(tmp / "one.json");
  EXPECT_EQ(find_user_embodiment("bolt_arm")->slot_begin, 230);
  spec = arm_spec("other_arm", 232);
  EXPECT_NE(refused(spec).find("overlaps 'bolt_arm'"), std::string::npos) << refused(spec);
  spec = arm_spec("bolt_arm", 230);
  spec["frame_stride"] = 4;
  EXPECT_NE(refused(spec).find("registered already"), std::string::npos) << refused(spec);
}

}  // namespace
}  // namespace dojo::data
