// LoRA post-training through the `dojo` executable: adapters and the action MLPs train, every
// other weight stays the init's bit for bit; the adapters sit apart under PEFT's names, resume,
// merge (`dojo ckpt merge`) and load for inference in either form with the same result.
#include <gtest/gtest.h>

#include <cmath>
#include <nlohmann/json.hpp>

#include "core/safetensors.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo {
namespace {

TEST(LoraCli, PostTrainsAdaptersAloneResumesMergesAndEvaluatesInEitherForm) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 3;
  g.frames = 26;
  g.val_episodes = 1;
  test::write_synthetic_dataset(tmp / "robot", g);
  const auto data = (tmp / "robot").string(), tok = (tmp / "tok").string();
  auto r = test::run_dojo("--threads 1 tokenizer train --data " + data + " --out " + tok +
                          " --steps 1 --batch 1 --frames 5 --size 32 --dim 8 --workers 1 --split all");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const std::string common = " --data " + data + " --tokenizer " + tok + " --batch 2 --hop 4 --save-every 2";
  r = test::run_dojo("--threads 1 wm train --stage scratch --steps 2" + common + " --out " +
                     (tmp / "s").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const std::string init = (tmp / "s" / "checkpoint").string();

  const std::string lora = "--threads 1 wm train --stage posttrain --lora 4 --lora-alpha 8 --lr 1e-2" +
                           common + " --init " + init + " --out " + (tmp / "l").string();
  r = test::run_dojo(lora + " --steps 3");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("trainable parameters (adapters and action MLPs)"), std::string::npos) << r.output;

  // Frozen: every base weight but the action MLPs is the init's, bit for bit.
  const auto before = SafetensorsFile::open(tmp / "s" / "checkpoint" / "model.safetensors");
  const auto after = SafetensorsFile::open(tmp / "l" / "checkpoint" / "model.safetensors");
  ASSERT_EQ(before.keys().size(), after.keys().size());
  int64_t compared = 0;
  for (const auto& name : before.keys()) {
    if (name.rfind("net.action_embedder", 0) == 0) continue;
    EXPECT_TRUE(torch::equal(before.tensor(name), after.tensor(name))) << name;
    ++compared;
  }
  EXPECT_GT(compared, 50);
  EXPECT_FALSE(torch::equal(before.tensor("net.action_embedder_B_D.fc1.weight"),
                            after.tensor("net.action_embedder_B_D.fc1.weight")));
  // The adapters, apart, under PEFT's names; trained (B starts at zero).
  const auto adapter = SafetensorsFile::open(tmp / "l" / "checkpoint" / "adapter_model.safetensors");
  const auto b = adapter.tensor("net.blocks.0.self_attn.q_proj.lora_B.default.weight");
  EXPECT_GT(b.abs().max().item<float>(), 0.f);
  EXPECT_EQ(adapter.tensor("net.blocks.0.mlp.layer1.lora_A.default.weight").size(0), 4);
  // No optimiser state for frozen weights.
  const auto state = SafetensorsFile::open(tmp / "l" / "checkpoint" / "trainer_state.safetensors");
  bool adapter_moments = false;
  for (const auto& name : state.keys()) {
    EXPECT_EQ(name.find("self_attn.q_proj.weight.exp_avg"), std::string::npos) << name;
    adapter_moments =
        adapter_moments || name.find("q_proj.lora_A.default.weight.exp_avg") != std::string::npos;
  }
  EXPECT_TRUE(adapter_moments);

  r = test::run_dojo(lora + " --steps 4");  // resumes
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("4 steps"), std::string::npos) << r.output;

  r = test::run_dojo("ckpt merge " + (tmp / "l" / "checkpoint").string() + " " + (tmp / "m").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_FALSE(std::filesystem::exists(tmp / "m" / "adapter_model.safetensors"));
  const auto merged_config = nlohmann::json::parse(test::read_file(tmp / "m" / "config.json"));
  EXPECT_FALSE(merged_config["config"].contains("lora"));
  EXPECT_TRUE(merged_config.contains("actions")) << "the action ranges stay";

  // Either form evaluates to the same scores.
  auto psnr = [&](const std::string& checkpoint) {
    const auto e = test::run_dojo("--threads 1 eval --checkpoint " + checkpoint + " --tokenizer " + tok +
                                  " --data " + data + " --split val --chunks 1 --steps 2 --json");
    EXPECT_EQ(e.exit_code, 0) << e.output;
    return nlohmann::json::parse(e.output.substr(e.output.find('{')))["splits"][0]["psnr"].get<double>();
  };
  EXPECT_NEAR(psnr((tmp / "l" / "checkpoint").string()), psnr((tmp / "m").string()), 0.05);

  r = test::run_dojo("wm train --stage scratch --lora 4 --steps 1" + common + " --out " +
                     (tmp / "x").string());
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("--stage posttrain"), std::string::npos) << r.output;
  r = test::run_dojo("wm train --stage posttrain --lora 4 --lora-targets q,w --init " + init + common +
                     " --out " + (tmp / "x").string());
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("unknown LoRA target 'w'"), std::string::npos) << r.output;
  r = test::run_dojo("ckpt merge " + init + " " + (tmp / "x").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("no adapter_model.safetensors"), std::string::npos) << r.output;
}

}  // namespace
}  // namespace dojo
