// End to end through the `dojo` executable: train a tokenizer and a world model on generated
// robot episodes, post-train from it, roll out, evaluate; and the whole demo on a tiny budget.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <nlohmann/json.hpp>

#include "core/safetensors.h"
#include "core/state_dict.h"
#include "eval/lpips.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo {
namespace {

TEST(WmCli, TrainPosttrainRolloutAndEvalOnGeneratedData) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 3;
  g.frames = 26;
  g.val_episodes = 1;  // one held-out episode
  test::write_synthetic_dataset(tmp / "robot", g);
  const auto data = (tmp / "robot").string(), tok = (tmp / "tok").string();
  auto r = test::run_dojo("--threads 1 tokenizer train --data " + data + " --out " + tok +
                          " --steps 2 --batch 1 --frames 5 --size 32 --dim 8 --workers 1 --split all");
  ASSERT_EQ(r.exit_code, 0) << r.output;

  const std::string common = " --data " + data + " --tokenizer " + tok + " --batch 2 --hop 4 --save-every 2";
  r = test::run_dojo("--threads 1 wm train --stage scratch --steps 3" + common + " --out " +
                     (tmp / "s").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "s" / "checkpoint" / "model.safetensors"));
  EXPECT_TRUE(std::filesystem::exists(tmp / "s" / "latents-0.safetensors"));
  EXPECT_NE(test::read_file(tmp / "s" / "loss.csv").find("\n3,"), std::string::npos);

  // Continuing to more steps resumes from the checkpoint.
  r = test::run_dojo("--threads 1 wm train --stage scratch --steps 4" + common + " --out " +
                     (tmp / "s").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("4 steps"), std::string::npos) << r.output;

  // Post-training in bf16 (CPU autocast); its float32 checkpoint is evaluated in fp32 below.
  // With the action-following levers on; the checkpoint keeps the robot data's action range, the
  // normalisation every later rollout uses.
  r = test::run_dojo("--threads 1 wm train --stage posttrain --steps 2 --precision bf16" + common +
                     " --condition-noise 0.3 --action-dropout 0.1 --motion-weight 1 --init " +
                     (tmp / "s" / "checkpoint").string() + " --out " + (tmp / "p").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto summary = nlohmann::json::parse(test::read_file(tmp / "p" / "train_summary.json"));
  EXPECT_EQ(summary.at("precision"), "bf16");
  EXPECT_EQ(summary.at("device"), "cpu");
  const auto config = nlohmann::json::parse(test::read_file(tmp / "p" / "checkpoint" / "config.json"));
  const auto stats =
      nlohmann::json::parse(test::read_file(tmp / "robot" / "info.json")).at("stats").at("action");
  ASSERT_TRUE(config.contains("actions")) << config.dump();
  EXPECT_EQ(config["actions"].begin().value().at("min"), stats.at("min"));
  EXPECT_EQ(config["actions"].begin().value().at("max"), stats.at("max"));

  // Post-training the post-trained model on other data of the same action slot continues it: the
  // action layer is not re-initialised (one step at a tiny rate leaves it where it was) and the
  // action ranges stay the model's, not the new data's.
  test::SyntheticOptions other = g;
  other.seed = 7;
  test::write_synthetic_dataset(tmp / "robot2", other);
  const auto other_stats =
      nlohmann::json::parse(test::read_file(tmp / "robot2" / "info.json")).at("stats").at("action");
  ASSERT_NE(other_stats.at("max"), stats.at("max"));
  // Another seed: a re-initialised layer would not land on the weights it had before. A weighted
  // mixture of the new data and the old: the weights and shares are recorded in the checkpoint.
  r = test::run_dojo("--threads 1 wm train --stage posttrain --steps 1 --lr 1e-9 --seed 1 --data " +
                     (tmp / "robot2").string() + ":3 --data " + data + " --tokenizer " + tok +
                     " --batch 2 --hop 4 --init " + (tmp / "p" / "checkpoint").string() + " --out " +
                     (tmp / "p2").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("continuing it"), std::string::npos) << r.output;
  const auto mixture = nlohmann::json::parse(
      test::read_file(tmp / "p2" / "checkpoint" / "trainer_state.json"))["extra"]["mixture"];
  ASSERT_EQ(mixture.size(), 2u) << mixture.dump();
  EXPECT_EQ(mixture[0].at("data"), (tmp / "robot2").string());
  EXPECT_EQ(mixture[0].at("weight"), 3.0);
  EXPECT_EQ(mixture[1].at("weight"), 1.0);
  EXPECT_DOUBLE_EQ(mixture[0].at("share").get<double>(), 0.75);
  const auto continued = nlohmann::json::parse(test::read_file(tmp / "p2" / "checkpoint" / "config.json"));
  EXPECT_EQ(continued.at("actions"), config.at("actions"));
  const std::string fc1 = "net.action_embedder_B_D.fc1.weight";
  const auto before = SafetensorsFile::open(tmp / "p" / "checkpoint" / "model.safetensors").tensor(fc1);
  const auto after = SafetensorsFile::open(tmp / "p2" / "checkpoint" / "model.safetensors").tensor(fc1);
  EXPECT_LT((after.to(torch::kFloat32) - before.to(torch::kFloat32)).abs().max().item<float>(), 1e-7)
      << "the action layer was re-initialised";

  // LPIPS with random weights: the wiring is what is tested here (values are checked in metrics_test).
  torch::manual_seed(0);
  eval::LpipsVgg lpips;
  save_safetensors(tmp / "lpips.safetensors", state_dict(*lpips));
  r = test::run_dojo("--threads 1 eval --checkpoint " + (tmp / "p" / "checkpoint").string() +
                     " --tokenizer " + tok + " --data " + data +
                     " --split val --split train --chunks 1 --steps 2 --json --out " +
                     (tmp / "eval").string() + " --lpips-weights " + (tmp / "lpips.safetensors").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto j = nlohmann::json::parse(r.output.substr(r.output.find('{')));
  ASSERT_EQ(j.at("splits").size(), 2u);
  EXPECT_EQ(j["splits"][0].at("split"), "val");
  EXPECT_EQ(j["splits"][0].at("videos"), 1);
  EXPECT_EQ(j["splits"][0].at("frames_per_video"), 13);
  EXPECT_GT(j["splits"][0].at("psnr").get<double>(), 0.0);
  EXPECT_TRUE(std::isfinite(j["splits"][0]["world_model"].at("lpips").get<double>()));  // random heads
  EXPECT_TRUE(j["splits"][0]["copy_frame"].contains("lpips"));
  EXPECT_GT(j["splits"][0]["tokenizer"].at("psnr").get<double>(), 0.0);
  EXPECT_TRUE(std::filesystem::exists(tmp / "eval" / "metrics.md"));
  EXPECT_FALSE(std::filesystem::is_empty(tmp / "eval" / "videos"));

  r = test::run_dojo("--threads 1 wm rollout --checkpoint " + (tmp / "p" / "checkpoint").string() +
                     " --tokenizer " + tok + " --data " + data +
                     " --chunks 2 --steps 2 --precision bf16 --out " + (tmp / "roll.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("25 frames"), std::string::npos) << r.output;

  // Mistakes are one clear line and a non-zero exit.
  r = test::run_dojo("wm train --stage posttrain --steps 2" + common + " --out " + (tmp / "q").string());
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("--init"), std::string::npos) << r.output;
  r = test::run_dojo("wm train --stage pretrain --steps 2" + common + " --out " + (tmp / "q").string());
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("LAM"), std::string::npos) << r.output;
  r = test::run_dojo("wm train --stage scratch --steps 2 --data " + data + ":0 --tokenizer " + tok +
                     " --out " + (tmp / "q").string());
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_NE(r.output.find("DIR:WEIGHT with WEIGHT > 0, got '" + data + ":0'"), std::string::npos) << r.output;
  r = test::run_dojo("eval --checkpoint " + tok + " --tokenizer " + tok + " --data " + data);
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("not a world-model checkpoint"), std::string::npos) << r.output;
}

TEST(WmCli, CudaOnACpuMachineAndBadPrecisionsFailInOneLine) {
  if (torch::cuda::is_available()) GTEST_SKIP() << "CUDA is available here";
  test::TempDir tmp;
  const auto d = (tmp / "none").string();  // nothing is read: the flags fail first
  std::vector<std::string> commands = {
      "wm train --data " + d + " --tokenizer " + d + " --out " + d,
      "wm rollout --checkpoint " + d + " --tokenizer " + d + " --data " + d + " --out " + d + ".mp4",
      "eval --checkpoint " + d + " --tokenizer " + d + " --data " + d};
#ifdef DOJO_WITH_SIM
  commands.push_back("demo --out " + d);
#endif
  for (const auto& command : commands) {
    const auto r = test::run_dojo(command + " --device cuda");
    EXPECT_EQ(r.exit_code, 2) << command << "\n" << r.output;
    EXPECT_EQ(r.output.rfind("error: device 'cuda' requested but CUDA is not available", 0), 0u) << r.output;
    EXPECT_EQ(std::count(r.output.begin(), r.output.end(), '\n'), 1) << r.output;
  }
  auto r = test::run_dojo(commands[0] + " --precision fp8");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_NE(r.output.find("unknown precision 'fp8'"), std::string::npos) << r.output;
  r = test::run_dojo(commands[0] + " --precision fp16");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_NE(r.output.find("loss scaling"), std::string::npos) << r.output;
  r = test::run_dojo(commands[1] + " --precision fp16");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_NE(r.output.find("fp16 needs a CUDA device"), std::string::npos) << r.output;
  EXPECT_FALSE(std::filesystem::exists(d));
}

#ifdef DOJO_WITH_SIM
TEST(WmCli, DemoRunsEndToEndOnTinyStepBudgetsAndReusesFinishedStages) {
  test::TempDir tmp;
  const auto out = (tmp / "demo").string();
  // 16 streamed frames: 4 steps, of which the rate counts those after the first two.
  const std::string command =
      "--threads 1 demo --lam-steps 3 --probe-steps 3 --pretrain-steps 3 "
      "--posttrain-steps 3 --warmup-steps 3 --self-forcing-steps 3 --fast-decoder-steps 3 --episodes 2 "
      "--eval-episodes 2 --frames 50 --sampler-steps 2 --workers 1 --max-clips 4 --eval-chunks 1 "
      "--stream-frames 16 --reference none --out " +
      out;
  // A tokenizer that is not one fails at once, before anything is generated.
  auto r = test::run_dojo(command + " --tokenizer " + (tmp / "no_tokenizer").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("no_tokenizer/config.json: missing"), std::string::npos) << r.output;
  EXPECT_FALSE(std::filesystem::exists(out));
  r = test::run_dojo(command + " --tokenizer-steps 3");  // steps for a tokenizer that is not trained
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_NE(r.output.find("give --tokenizer train with it"), std::string::npos) << r.output;
  EXPECT_FALSE(std::filesystem::exists(out));

  // By default the shipped tokenizer is copied in, not trained.
  r = test::run_dojo(command);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("expected ~"), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find("tokenizer train:"), std::string::npos) << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "demo" / "tokenizer" / "checkpoint" / "model.safetensors"));
  // Self-Forcing reads the warm-up's 49-frame latent cache instead of encoding the clips again.
  EXPECT_NE(r.output.find("clips from " + out + "/student/latents-long-0.safetensors"), std::string::npos)
      << r.output;
  const auto html = test::read_file(tmp / "demo" / "report.html");
  EXPECT_NE(html.find("data:video/mp4;base64,"), std::string::npos);
  EXPECT_NE(html.find("<polyline"), std::string::npos);
  EXPECT_NE(html.find("Does the model use the actions?"), std::string::npos);
  for (const char* split : {"val", "ood-objects", "counterfactual"})
    EXPECT_NE(html.find(std::string("<td>") + split + "</td>"), std::string::npos) << split;
  EXPECT_NE(html.find("trained beforehand"), std::string::npos);
  const auto demo = nlohmann::json::parse(test::read_file(tmp / "demo" / "demo.json"));
  EXPECT_TRUE(demo["tokenizer"]["result"].contains("copied_from")) << demo["tokenizer"].dump();
  ASSERT_EQ(demo["eval"]["result"].size(), 3u);
  EXPECT_TRUE(demo["eval"]["result"][0].contains("shuffled_actions"));
  EXPECT_TRUE(demo["eval"]["result"][0]["world_model"].contains("keypoint_error_px"));
  EXPECT_EQ(demo["wm_posttrain"]["result"].at("steps").get<int>(), 3);
  // The student: distilled, scored on the same splits, timed streaming.
  EXPECT_NE(html.find("The real-time student"), std::string::npos);
  ASSERT_EQ(demo["eval_student"]["result"]["splits"].size(), 3u);
  EXPECT_TRUE(demo["eval_student"]["result"]["splits"][0]["world_model"].contains("keypoint_error_px"));
  EXPECT_GT(demo["eval_student"]["result"]["streaming"].at("frames_per_second").get<double>(), 0.0);
  EXPECT_EQ(demo["student"]["result"].at("self_forcing_iterations").get<int>(), 3);

  // Running it again re-uses every stage: nothing trains, the records stay, the report is rewritten.
  const auto posttrain = test::read_file(tmp / "demo" / "stages" / "wm_posttrain.json");
  std::filesystem::remove(tmp / "demo" / "report.html");
  r = test::run_dojo(command);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(r.output.find("lam train:"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("re-using it"), std::string::npos) << r.output;
  EXPECT_EQ(test::read_file(tmp / "demo" / "stages" / "wm_posttrain.json"), posttrain);
  EXPECT_TRUE(std::filesystem::exists(tmp / "demo" / "report.html"));
}
#endif  // DOJO_WITH_SIM

}  // namespace
}  // namespace dojo
