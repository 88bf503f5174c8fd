// LoRA adapters on the DiT: PEFT's names and shapes, a fresh adapter changes nothing, the merged
// weights compute what the adapted network computes, and checkpoints keep adapters apart and fold
// them in at load.
#include "models/lora.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <ATen/CPUGeneratorImpl.h>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/state_dict.h"
#include "models/dit.h"
#include "test_util.h"
#include "train/wm_test_fixtures.h"

namespace dojo::models {
namespace {

// The training tests' tiny DiT (64 wide, 2 blocks) with live action MLPs.
DitConfig tiny_config() { return train::test_fixtures::tiny_dit(/*live_actions=*/true, 64); }

DitInputs inputs() {
  auto g = at::make_generator<at::CPUGeneratorImpl>(11);
  DitInputs in;
  in.x = torch::randn({1, 16, 2, 4, 4}, g);
  in.timesteps = torch::full({1, 2}, 0.5);
  in.condition_mask = torch::zeros({1, 1, 2, 4, 4});
  in.padding_mask = torch::zeros({1, 1, 4, 4});
  in.actions = torch::randn({1, 4, 384}, g);
  in.context = torch::zeros({1, 1, 16});
  return in;
}

torch::Tensor velocity(ActionDit& net) {
  torch::NoGradGuard no_grad;
  net->eval();
  return net->forward(inputs());
}

TEST(Lora, AdaptersStartAsTheBaseAndMergeIntoTheSameNetwork) {
  test::OneThread one;
  torch::manual_seed(3);
  ActionDit base(tiny_config());
  auto config = base->config;
  config.lora.rank = 4;
  config.lora.alpha = 8;
  ActionDit adapted(config);
  LoadOptions lenient;
  lenient.strict = false;
  load_state_dict(*adapted, state_dict(*base), lenient);

  auto params = adapted->named_parameters();
  ASSERT_TRUE(params.contains("blocks.0.self_attn.q_proj.lora_A.default.weight"));
  EXPECT_EQ(params["blocks.0.cross_attn.k_proj.lora_A.default.weight"].sizes(),
            (std::vector<int64_t>{4, config.crossattn_dim()}));
  EXPECT_EQ(params["blocks.1.mlp.layer2.lora_B.default.weight"].sizes(),
            (std::vector<int64_t>{config.model_channels, 4}));
  int64_t adapters = 0;
  for (const auto& item : params) adapters += is_lora_name(item.key());
  EXPECT_EQ(adapters, 2 * 2 * (4 + 4 + 2));  // blocks x (A, B) x (self q k v o, cross q k v o, mlp 1 2)
  EXPECT_TRUE(torch::equal(velocity(adapted), velocity(base))) << "a fresh adapter (B = 0) changes nothing";

  {
    torch::NoGradGuard no_grad;
    for (auto& item : adapted->named_parameters())
      if (is_lora_name(item.key())) item.value().normal_(0, 0.05);
  }
  const auto want = velocity(adapted);
  EXPECT_GT((want - velocity(base)).abs().max().item<double>(), 1e-3);
  auto [weights, lora] = split_lora(state_dict(*adapted));
  fold_lora(weights, lora, config.lora.alpha, "test");
  ActionDit merged(base->config);
  load_state_dict(*merged, weights);
  EXPECT_LT((velocity(merged) - want).abs().max().item<double>(), 1e-5);

  // A checkpoint keeps the adapters apart under PEFT's names and folds them in at load.
  test::TempDir dir;
  save_checkpoint(dir / "ckpt", world_model_checkpoint(*adapted));
  const auto ckpt = Checkpoint::open(dir / "ckpt");
  ASSERT_TRUE(ckpt.has_adapter());
  EXPECT_TRUE(ckpt.adapter().contains("net.blocks.0.self_attn.q_proj.lora_A.default.weight"));
  EXPECT_FALSE(ckpt.model().contains("net.blocks.0.self_attn.q_proj.lora_A.default.weight"));
  EXPECT_EQ(ckpt.adapter().metadata().at("lora_rank"), "4");
  auto loaded = load_world_model(dir / "ckpt");
  EXPECT_FALSE(loaded->config.lora.enabled());
  EXPECT_LT((velocity(loaded) - want).abs().max().item<double>(), 1e-5);
  EXPECT_EQ(DitConfig::from_json(ckpt.config()["config"]).lora.rank, 4);
}

TEST(Lora, ConfigAndTargetsAreChecked) {
  EXPECT_EQ(LoraConfig::parse_targets("q,v,mlp2,q"), (std::vector<std::string>{"q", "v", "mlp2"}));
  EXPECT_EQ(test::error_message([] { LoraConfig::parse_targets("q,w"); }),
            "unknown LoRA target 'w' (q, k, v, o, mlp1, mlp2)");
  EXPECT_NE(test::error_message([] {
              LoraConfig::from_json({{"rank", 0}}, "cfg");
            }).find("positive"),
            std::string::npos);
  auto config = tiny_config();
  EXPECT_FALSE(config.to_json().contains("lora")) << "configs without adapters keep their fingerprint";
  config.lora.rank = 8;
  config.lora.targets = {"q", "v"};
  const auto back = DitConfig::from_json(config.to_json());
  EXPECT_EQ(back.lora.rank, 8);
  EXPECT_EQ(back.lora.targets, (std::vector<std::string>{"q", "v"}));
  ActionDit net(back);
  const auto params = net->named_parameters();
  EXPECT_TRUE(params.contains("blocks.0.self_attn.v_proj.lora_B.default.weight"));
  EXPECT_FALSE(params.contains("blocks.0.self_attn.k_proj.lora_A.default.weight"));
  EXPECT_FALSE(params.contains("blocks.0.mlp.layer1.lora_A.default.weight"));
}

}  // namespace
}  // namespace dojo::models
