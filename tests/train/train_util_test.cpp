#include "train/train_util.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "core/checkpoint.h"
#include "core/state_dict.h"
#include "test_util.h"

namespace dojo::train {
namespace {

// A plain AdamW loop saved after 3 steps and resumed continues exactly as the unbroken run.
TEST(TrainUtil, AdamwCheckpointsResumeExactly) {
  const auto batch = torch::randn({4, 3});
  const auto run_steps = [&](torch::nn::Linear& net, torch::optim::AdamW& opt, int n) {
    for (int i = 0; i < n; ++i) {
      opt.zero_grad();
      net(batch).pow(2).mean().backward();
      opt.step();
    }
  };
  const auto checkpoint = [](const torch::nn::Linear& net) {
    CheckpointData data;
    data.config = {{"model", "linear"}};
    for (const auto& [name, t] : state_dict(*net)) data.model.emplace_back("net." + name, t);
    return data;
  };
  torch::manual_seed(0);
  torch::nn::Linear a(3, 2);
  torch::optim::AdamW opt_a(a->parameters(), torch::optim::AdamWOptions(1e-2));
  run_steps(a, opt_a, 3);
  test::TempDir dir;
  save_with_adamw(dir / "ck", checkpoint(a), opt_a, *a, 3);
  run_steps(a, opt_a, 2);

  torch::manual_seed(1);  // other initial weights: the checkpoint must replace them
  torch::nn::Linear b(3, 2);
  torch::optim::AdamW opt_b(b->parameters(), torch::optim::AdamWOptions(1e-2));
  EXPECT_EQ(resume_with_adamw(dir / "ck", *b, "net.", opt_b), 3);
  run_steps(b, opt_b, 2);
  EXPECT_TRUE(torch::allclose(a->weight, b->weight, 0, 1e-7));
  EXPECT_TRUE(torch::allclose(a->bias, b->bias, 0, 1e-7));
}

}  // namespace
}  // namespace dojo::train
