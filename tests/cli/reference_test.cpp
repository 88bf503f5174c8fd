// The shipped reference model set (models/reference): every member loads (the real-time student and
// its fast decoder among them), the world model carries its action ranges and time shift, and
// `dojo wm rollout` uses the set when no --checkpoint is given. A clone without the set fails
// here: it is part of the repository.
#include <gtest/gtest.h>

#include <filesystem>
#include <nlohmann/json.hpp>

#include "synthetic_data.h"
#include "test_util.h"

namespace dojo {
namespace {

const std::filesystem::path kReference = std::filesystem::path(DOJO_SOURCE_DIR) / "models" / "reference";

TEST(Reference, EveryModelLoadsAsItsKind) {
  const std::pair<const char*, const char*> members[] = {{"lam", "lam"},
                                                         {"tokenizer", "wan21_vae"},
                                                         {"probe", "keypoint_probe"},
                                                         {"wm_posttrain", "action_dit"},
                                                         {"student", "action_dit"}};
  for (const auto& [dir, kind] : members) {
    const auto r = test::run_dojo("ckpt info " + (kReference / dir).string() + " --json");
    ASSERT_EQ(r.exit_code, 0) << dir << ": " << r.output;
    const auto info = nlohmann::json::parse(r.output);
    EXPECT_EQ(info["config"].at("model"), kind) << dir;
    EXPECT_FALSE(info.contains("trainer_state") && !info["trainer_state"].is_null())
        << dir << ": inference export";
    EXPECT_TRUE(info["model"]["dtypes"].contains("BF16")) << dir;
  }
  const auto posttrain = nlohmann::json::parse(test::read_file(kReference / "wm_posttrain" / "config.json"));
  EXPECT_TRUE(posttrain.at("actions").contains("dojosim_robot"));
  EXPECT_GT(posttrain.at("sampler").at("shift").get<double>(), 0.0);
}

// The real-time student every streaming command uses by default: an inference export with its
// streaming settings and the teacher's action ranges, and the fast decoder of the set's tokenizer.
TEST(Reference, TheStudentAndItsFastDecoderAreShipped) {
  const auto r = test::run_dojo("ckpt info " + (kReference / "student").string() + " --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto info = nlohmann::json::parse(r.output);
  EXPECT_TRUE(info["config"].at("student").is_object()) << "config.json's \"student\" entry";
  EXPECT_TRUE(info["config"].at("actions").contains("dojosim_robot"));
  const auto decoder = test::run_dojo("ckpt info " + (kReference / "fast_decoder").string() + " --json");
  ASSERT_EQ(decoder.exit_code, 0) << decoder.output;
  EXPECT_EQ(nlohmann::json::parse(decoder.output)["config"].at("model"), "fast_decoder");
}

TEST(Reference, RolloutUsesTheReferenceSetByDefault) {
  test::OneThread one;
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 1;
  g.frames = 14;
  g.size = 64;
  test::write_synthetic_dataset(tmp / "robot", g);
  const auto r = test::run_dojo("--threads 1 wm rollout --data " + (tmp / "robot").string() +
                                " --split all --chunks 1 --steps 2 --out " + (tmp / "roll.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("reference"), std::string::npos) << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "roll.mp4"));
}

}  // namespace
}  // namespace dojo
