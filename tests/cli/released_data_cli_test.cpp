// Bring your own weights and robot data, end to end through the command line: a DiT file written by
// PyTorch (the release converter's model_ema_bf16.pt form) and a Wan2.1 VAE .pth converted, then
// rolled out, evaluated and streamed on a LeRobot GR-1 set written by real Parquet and video
// writers, with actions in the robot's own units and the robot named on the command line.
#include <fstream>
#include <nlohmann/json.hpp>

#include "data/lerobot_writer.h"
#include "test_util.h"

namespace dojo {
namespace {

namespace fx = data::lerobot_fixture;

// A JSON file of `rows` raw GR-1 commands of `width` values.
std::string write_raw_actions(const test::TempDir& tmp, const std::string& name, int rows, int width) {
  nlohmann::json j = nlohmann::json::array();
  for (int r = 0; r < rows; ++r) {
    std::vector<float> row(width);
    for (int d = 0; d < width; ++d) row[d] = fx::raw_action(0, 40 - 2 * r, d);  // the arm moving back
    j.push_back(row);
  }
  std::ofstream(tmp / name) << nlohmann::json{{"actions", j}}.dump();
  return (tmp / name).string();
}

TEST(ReleasedDataCli, ConvertedModelRollsOutEvaluatesAndStreamsALeRobotSetInRawUnits) {
  test::TempDir tmp;
  auto r = test::run_dojo("convert " + (test::torch_files_dir() / "dit_action384_ema_bf16.pt").string() +
                          " " + (tmp / "dit").string() + " --dtype fp32");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo("convert " + (test::torch_files_dir() / "wan_vae.pth").string() + " " +
                     (tmp / "vae").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  fx::Fixture unnamed;
  unnamed.robot_type = "";  // a path that says GR-1, a robot_type that says nothing
  unnamed.frames = 100;     // `wm stream` replays 4 chunks: 49 frames at stride 2
  const auto lerobot = fx::make_lerobot(tmp / "PhysicalAI-Robotics-GR00T-Teleop-GR1", unnamed);
  const std::string model = "--checkpoint " + (tmp / "dit").string() + " --tokenizer " +
                            (tmp / "vae").string() + " --data " + lerobot.string();

  // Nobody named the robot: refused in one line, never guessed from the path.
  r = test::run_dojo("--threads 1 wm rollout " + model + " --steps 2 --split train --chunks 1 --out " +
                     (tmp / "r.mp4").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("name the robot with --embodiment"), std::string::npos) << r.output;

  const std::string gr1 = model + " --embodiment gr1 --split train";
  const std::string rollout = "--threads 1 wm rollout --steps 2 --chunks 1 " + gr1;
  r = test::run_dojo(rollout + " --out " + (tmp / "r.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("slot gr1 (29 actions), dataset normalisation, frame stride 2"), std::string::npos)
      << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "r.mp4"));

  // Counterfactual commands in GR-1's units.
  r = test::run_dojo(rollout + " --actions " + write_raw_actions(tmp, "raw.json", 12, 29) + " --out " +
                     (tmp / "cf.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "cf.mp4"));
  r = test::run_dojo(rollout + " --actions " + write_raw_actions(tmp, "narrow.json", 12, 28) + " --out " +
                     (tmp / "bad.mp4").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("must be 12 K rows of 29 values"), std::string::npos) << r.output;
  r = test::run_dojo(rollout + " --action-norm model --out " + (tmp / "bad.mp4").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("records no action range for slot 'gr1'"), std::string::npos) << r.output;

  // Evaluation with action sensitivity on both episodes.
  r = test::run_dojo("--threads 1 eval --steps 2 " + model +
                     " --embodiment gr1 --split train --chunks 1 --episodes 2 "
                     "--action-sensitivity --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto report = nlohmann::json::parse(r.output.substr(r.output.find("{\n")));
  const auto& split = report["splits"][0];
  EXPECT_EQ(split["videos"], 2);
  EXPECT_EQ(split["frames_per_video"], 13);
  EXPECT_NE(split["data"].get<std::string>().find("lerobot-v2.1, robot, slot gr1"), std::string::npos);
  EXPECT_GT(split["world_model"]["psnr"].get<double>(), 0);
  EXPECT_TRUE(split.contains("shuffled_actions"));

  // Streaming: the recorded actions, then raw command lines of 4 rows each.
  r = test::run_dojo("--threads 1 wm stream " + gr1 + " --frames 8 --out " + (tmp / "s.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  std::ofstream lines(tmp / "lines.jsonl");
  for (int chunk = 0; chunk < 2; ++chunk) {
    nlohmann::json rows = nlohmann::json::array();
    for (int k = 0; k < 4; ++k) {
      std::vector<float> row(29);
      for (int d = 0; d < 29; ++d) row[d] = fx::raw_action(0, 2 * (4 * chunk + k + 1), d);
      rows.push_back(row);
    }
    lines << rows.dump() << "\n";
  }
  lines.close();
  r = test::run_dojo("--threads 1 wm stream " + gr1 + " --frames 8 --actions " +
                     (tmp / "lines.jsonl").string() + " --out " + (tmp / "s2.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "s2.mp4"));
}

}  // namespace
}  // namespace dojo
