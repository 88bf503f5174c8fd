#include "models/released_import.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <filesystem>
#include <nlohmann/json.hpp>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/safetensors.h"
#include "models/dit.h"
#include "models/lam.h"
#include "models/wan_vae.h"
#include "test_util.h"

namespace dojo::models {
namespace {

namespace fs = std::filesystem;

SafetensorsFile open_golden(const std::string& name) {
  return SafetensorsFile::open(test::golden_dir() / name);
}

// The golden tiny DiT's velocity for the shared-timestep case, and the converted model's.
double golden_forward_error(const fs::path& checkpoint) {
  const auto io = open_golden("dit_tiny_io.safetensors");
  ActionDit net = load_world_model(checkpoint);
  DitInputs in;
  in.x = io.tensor("x_t");
  in.timesteps = io.tensor("tshared_timesteps");
  in.condition_mask = io.tensor("condition_mask");
  in.padding_mask = io.tensor("padding_mask");
  in.actions = io.tensor("action");
  in.context = io.tensor("crossattn_emb");
  torch::NoGradGuard no_grad;
  const auto velocity = net->forward(in);
  return (velocity - io.tensor("tshared_velocity")).abs().max().item<double>();
}

TEST(ReleasedImport, DcpFolderGivesTheGoldenForwardFromItsEmaWeights) {
  test::OneThread one_thread;
  test::TempDir tmp;
  const auto report = import_released(test::dcp_fixture_dir() / "checkpoints", tmp / "dit", {});
  EXPECT_EQ(report.model, "action_dit");
  EXPECT_EQ(report.source_format, "dcp");
  EXPECT_EQ(report.selection, "net_ema");
  EXPECT_EQ(report.config["config"], DitConfig::golden_tiny().to_json());
  EXPECT_LE(golden_forward_error(tmp / "dit"), 1e-4);
  // Every weight is the golden one, bit for bit.
  const auto ours = Checkpoint::open(tmp / "dit");
  const auto want = open_golden("dit_tiny_weights.safetensors");
  for (const auto& name : want.keys())
    EXPECT_TRUE(torch::equal(ours.model().tensor(name), want.tensor(name))) << name;

  // --trained takes net.* (the golden weights halved): not the golden forward.
  ImportOptions trained;
  trained.trained = true;
  EXPECT_EQ(import_released(test::dcp_fixture_dir() / "checkpoints", tmp / "trained", trained).selection,
            "net");
  EXPECT_GT(golden_forward_error(tmp / "trained"), 1e-2);
}

TEST(ReleasedImport, TheReleaseConvertersBf16FileHoldsTheGoldenWeightsInBf16) {
  test::OneThread one_thread;
  test::TempDir tmp;
  const auto report = import_released(test::dcp_fixture_dir() / "model_ema_bf16.pt", tmp / "dit", {});
  EXPECT_EQ(report.source_format, "zip");
  const auto expected = nlohmann::json::parse(test::read_file(test::dcp_fixture_dir() / "EXPECTED.json"));
  const auto ours = Checkpoint::open(tmp / "dit");
  const auto want = open_golden("dit_tiny_weights.safetensors");
  for (const auto& [name, e] : expected["keys"].items()) {
    const auto t = ours.model().tensor(name);
    const auto g = want.tensor(name);
    EXPECT_TRUE(torch::equal(t, g.is_floating_point() ? g.to(torch::kBFloat16) : g)) << name;
    EXPECT_NEAR(t.to(torch::kFloat64).sum().item<double>(), e["sum_bf16"].get<double>(),
                1e-3 * (1 + std::abs(e["sum_bf16"].get<double>())))
        << name;
  }
  EXPECT_TRUE(
      report.config["config"]["rope_bf16_ranges"].get<bool>());  // as the release's bf16 file computes
  EXPECT_LE(golden_forward_error(tmp / "dit"), 0.5);             // bf16 weights: close, not exact
}

TEST(ReleasedImport, PeftAdaptersMergeIntoTheFullWeightsOrStayApart) {
  test::OneThread one_thread;
  test::TempDir tmp;
  const auto file = test::torch_files_dir() / "dit_lora.pt";
  ImportOptions options;
  options.lora_alpha = 8.0;  // the file's rank 4, alpha 8
  const auto merged = import_released(file, tmp / "merged", options);
  EXPECT_EQ(merged.lora_adapters, 20);  // q/k/v/output_proj of both attentions + 2 MLP layers, x 2 blocks
  EXPECT_LE(golden_forward_error(tmp / "merged"), 1e-4);
  // The wrong alpha is a different model.
  options.lora_alpha = 32.0;
  import_released(file, tmp / "wrong_alpha", options);
  EXPECT_GT(golden_forward_error(tmp / "wrong_alpha"), 1e-2);

  options.lora_alpha = 8.0;
  options.merge_lora = false;
  const auto kept = import_released(file, tmp / "kept", options);
  EXPECT_EQ(kept.lora_adapters, 20);
  const auto adapters = SafetensorsFile::open(tmp / "kept" / "adapter_model.safetensors");
  EXPECT_EQ(adapters.keys().size(), 40u);
  EXPECT_TRUE(adapters.contains("net.blocks.0.self_attn.q_proj.lora_A.default.weight"));
  const auto kept_ckpt = Checkpoint::open(tmp / "kept");
  EXPECT_TRUE(kept_ckpt.has_adapter());
  EXPECT_TRUE(kept_ckpt.model().contains("net.blocks.0.self_attn.q_proj.weight"));
  EXPECT_FALSE(kept_ckpt.model().contains("net.blocks.0.self_attn.q_proj.lora_A.default.weight"));
  // Inference loads the kept form too: the adapters folded in at load give the golden forward...
  EXPECT_LE(golden_forward_error(tmp / "kept"), 1e-4);
  // ... which the base alone does not.
  fs::remove(tmp / "kept" / "adapter_model.safetensors");
  EXPECT_GT(golden_forward_error(tmp / "kept"), 1e-3);
}

TEST(ReleasedImport, LightningLamCheckpointGivesTheGoldenLam) {
  test::OneThread one_thread;
  test::TempDir tmp;
  const auto report = import_released(test::torch_files_dir() / "lightning.ckpt", tmp / "lam", {});
  EXPECT_EQ(report.model, "lam");
  const auto config = LamConfig::from_json(report.config);
  const auto tiny = LamConfig::tiny();
  EXPECT_EQ(config.model_dim, tiny.model_dim);
  EXPECT_EQ(config.num_heads, tiny.num_heads);
  EXPECT_EQ(config.patch_size, tiny.patch_size);
  EXPECT_EQ(config.latent_dim, tiny.latent_dim);
  EXPECT_EQ(config.enc_blocks, tiny.enc_blocks);
  EXPECT_EQ(config.dec_blocks, tiny.dec_blocks);
  const auto ours = Checkpoint::open(tmp / "lam");
  const auto want = open_golden("lam_tiny_weights.safetensors");
  EXPECT_EQ(ours.model().keys().size(), want.keys().size());
  for (const auto& name : want.keys())
    EXPECT_TRUE(torch::equal(ours.model().tensor(name), want.tensor(name))) << name;
  EXPECT_NO_THROW(load_lam(tmp / "lam"));
}

TEST(ReleasedImport, WanVaeStateDictGivesTheGoldenTokenizer) {
  test::OneThread one_thread;
  test::TempDir tmp;
  const auto report = import_released(test::torch_files_dir() / "wan_vae.pth", tmp / "vae", {});
  EXPECT_EQ(report.model, "wan21_vae");
  EXPECT_EQ(report.source_format, "legacy");
  EXPECT_EQ(report.config["config"], WanVaeConfig::tiny().to_json());
  const auto ours = Checkpoint::open(tmp / "vae");
  const auto want = open_golden("wan21_vae_tiny_weights.safetensors");
  for (const auto& name : want.keys())
    EXPECT_TRUE(torch::equal(ours.model().tensor(name), want.tensor(name))) << name;
  EXPECT_NO_THROW(load_tokenizer(tmp / "vae"));
}

TEST(ReleasedImport, FilesOfNoKnownModelAreNamedAsSuch) {
  test::TempDir tmp;
  const std::string message = test::error_message(
      [&] { import_released(test::torch_files_dir() / "tensors_zip.pt", tmp / "x", {}); });
  EXPECT_NE(message.find("neither a DreamDojo DiT, a LAM nor a Wan2.1 VAE"), std::string::npos) << message;
  EXPECT_FALSE(fs::exists(tmp / "x"));
}

}  // namespace
}  // namespace dojo::models
