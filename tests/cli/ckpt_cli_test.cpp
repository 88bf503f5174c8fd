// `dojo ckpt info`: JSON and table output for checkpoint directories and .safetensors files,
// one-line errors for missing or corrupt input.
#include <fstream>
#include <nlohmann/json.hpp>

#include "core/checkpoint.h"
#include "models/wan_vae.h"
#include "test_util.h"

namespace dojo {
namespace {

CheckpointData small_checkpoint() {
  CheckpointData data;
  data.config = {{"dim", 4}, {"name", "tiny"}};
  data.model = {{"net.proj.weight", torch::zeros({4, 3})},
                {"net.proj.bias", torch::zeros({4}, torch::kBFloat16)},
                {"net.accum_iteration", torch::zeros({}, torch::kInt64)}};
  TrainerState trainer;
  trainer.step = 250;
  trainer.extra = {{"epoch", 2}};
  trainer.tensors = {{"optim.net.proj.weight.exp_avg", torch::zeros({4, 3})}};
  data.trainer = trainer;
  return data;
}

TEST(CkptCli, InfoJsonOfACheckpoint) {
  test::TempDir dir;
  save_checkpoint(dir / "ckpt", small_checkpoint());
  const auto result = test::run_dojo("ckpt info " + (dir / "ckpt").string() + " --json");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto info = nlohmann::json::parse(result.output);
  EXPECT_EQ(info["format"], "checkpoint");
  EXPECT_EQ(info["num_params"], 12 + 4 + 1);
  EXPECT_EQ(info["config"]["name"], "tiny");
  EXPECT_EQ(info["trainer_state"]["step"], 250);
  EXPECT_EQ(info["trainer_state"]["extra"]["epoch"], 2);
  EXPECT_EQ(info["trainer_state"]["tensors"]["num_tensors"], 1);
  const auto& model = info["model"];
  EXPECT_EQ(model["num_tensors"], 3);
  EXPECT_EQ(model["file_size"], std::filesystem::file_size(dir / "ckpt" / "model.safetensors"));
  EXPECT_EQ(model["dtypes"]["F32"]["params"], 12);
  EXPECT_EQ(model["dtypes"]["BF16"]["tensors"], 1);
  EXPECT_EQ(model["dtypes"]["I64"]["params"], 1);
  EXPECT_EQ(nlohmann::json::parse(model["metadata"]["config"].get<std::string>())["dim"], 4);
  ASSERT_EQ(model["tensors"].size(), 3u);
  EXPECT_EQ(model["tensors"][0]["name"], "net.proj.weight");
  EXPECT_EQ(model["tensors"][0]["dtype"], "F32");
  EXPECT_EQ(model["tensors"][0]["shape"], nlohmann::json::array({4, 3}));
  EXPECT_EQ(model["tensors"][2]["shape"], nlohmann::json::array());
}

TEST(CkptCli, InfoTableOfACheckpoint) {
  test::TempDir dir;
  save_checkpoint(dir / "ckpt", small_checkpoint());
  const auto result = test::run_dojo("ckpt info " + (dir / "ckpt").string());
  ASSERT_EQ(result.exit_code, 0) << result.output;
  for (const char* needle :
       {"checkpoint", "parameters  17", "step 250", "net.proj.weight", "BF16", "[4, 3]", "\"tiny\""})
    EXPECT_NE(result.output.find(needle), std::string::npos) << needle << "\n" << result.output;
}

TEST(CkptCli, InfoOfGoldenSafetensorsFile) {
  const auto lam = test::golden_dir() / "lam_tiny_weights.safetensors";
  ASSERT_TRUE(std::filesystem::exists(lam)) << lam << " is missing";
  const auto result = test::run_dojo("ckpt info " + lam.string() + " --json");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto info = nlohmann::json::parse(result.output);
  EXPECT_EQ(info["format"], "safetensors");
  EXPECT_EQ(info["model"]["num_tensors"], 91);
  EXPECT_EQ(info["model"]["file_size"], std::filesystem::file_size(lam));
  int64_t total = 0;
  for (const auto& tensor : info["model"]["tensors"]) total += tensor["params"].get<int64_t>();
  EXPECT_EQ(info["num_params"], total);
  EXPECT_TRUE(info["model"]["metadata"].contains("config"));
}

TEST(CkptCli, MissingOrCorruptInputIsAOneLineError) {
  test::TempDir dir;
  { std::ofstream(dir / "junk.safetensors") << "this is not a safetensors file"; }
  for (const std::string name : {"nothing_here", "junk.safetensors"}) {
    const auto result = test::run_dojo("ckpt info " + (dir / name).string());
    EXPECT_EQ(result.exit_code, 1) << result.output;
    EXPECT_NE(result.output.find(name), std::string::npos) << result.output;
    EXPECT_EQ(result.output.rfind("error: ", 0), 0u) << result.output;
    EXPECT_EQ(std::count(result.output.begin(), result.output.end(), '\n'), 1) << result.output;
  }
  EXPECT_EQ(test::run_dojo("ckpt info").exit_code, 2);
}

// An inference export keeps the config, drops the trainer state, stores the learned parameters
// in bf16 and still loads as the same model, whose decoder output moves only by bf16 rounding.
TEST(CkptCli, ExportWritesABf16ModelThatStillLoads) {
  test::OneThread one;
  test::TempDir dir;
  torch::manual_seed(0);
  models::WanVae vae(models::WanVaeConfig::tiny());
  vae->eval();
  models::save_tokenizer(dir / "vae", *vae);
  const auto result = test::run_dojo("ckpt export " + (dir / "vae").string() + " " + (dir / "out").string());
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto exported = Checkpoint::open(dir / "out");
  EXPECT_FALSE(exported.has_trainer_state());
  EXPECT_EQ(exported.config(), Checkpoint::open(dir / "vae").config());
  size_t bf16 = 0;
  for (const auto& name : exported.model().keys())
    bf16 += exported.model().tensor(name, /*copy=*/true).scalar_type() == torch::kBFloat16;
  EXPECT_GT(bf16, 0u);

  auto reloaded = models::load_tokenizer(dir / "out");
  torch::NoGradGuard no_grad;
  const auto video = torch::rand({1, 3, 5, 16, 16}) * 2 - 1;  // [B, 3, T, H, W]
  const auto a = models::reconstruct(vae, video), b = models::reconstruct(reloaded, video);
  EXPECT_GT((a - b).abs().max().item<float>(), 0.f) << "bf16 weights change the output a little";
  EXPECT_LT((a - b).abs().max().item<float>(), 0.1f);

  const auto bad = test::run_dojo("ckpt export " + (dir / "nothing").string() + " " + (dir / "x").string());
  EXPECT_EQ(bad.exit_code, 1) << bad.output;
  EXPECT_NE(bad.output.find("nothing"), std::string::npos) << bad.output;
}

}  // namespace
}  // namespace dojo
