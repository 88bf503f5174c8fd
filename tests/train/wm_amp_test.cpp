// Mixed precision of the world model on CPU (bf16 autocast): the DiT forward, training with
// float32 master weights and checkpoints, and rollouts. The CUDA path is the same code with
// another device; it is not exercised here.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <ATen/CPUGeneratorImpl.h>

#include <cmath>
#include <cstdio>

#include "core/autocast.h"
#include "core/safetensors.h"
#include "infer/world_model.h"
#include "test_util.h"
#include "train/wm_train.h"
#include "wm_test_fixtures.h"

namespace dojo::train {
namespace {

using test::TempDir;

using test_fixtures::action_driven_latents;
using test_fixtures::gen;

// The tiny DiT of wm_train_test, with the action path live from the start.
models::DitConfig amp_dit() { return test_fixtures::tiny_dit(/*live_actions=*/true); }

double relative_l2(const torch::Tensor& got, const torch::Tensor& want) {
  return ((got.to(torch::kFloat32) - want).norm() / want.norm()).item<double>();
}

TEST(WmAmp, DitForwardUnderBf16AutocastAgreesWithFloat32) {
  test::OneThread one;
  torch::manual_seed(0);
  models::ActionDit net(amp_dit());
  net->eval();
  auto g = gen(1);
  models::DitInputs in;
  in.x = torch::randn({2, 16, 4, 8, 8}, g);
  in.timesteps = torch::tensor({250.0f, 800.0f}).view({2, 1});
  in.condition_mask = torch::zeros({2, 1, 4, 8, 8});
  in.condition_mask.select(2, 0).fill_(1);
  in.actions = torch::rand({2, 12, 384}, g) * 2 - 1;
  torch::NoGradGuard no_grad;
  const auto exact = net->forward(in);  // [2, 16, 4, 8, 8]
  torch::Tensor low;
  {
    AutocastGuard autocast(torch::kCPU, Precision::kBFloat16);
    low = net->forward(in);
  }
  // The output projection ran in bf16 (autocast was really on); the weights are still float32.
  EXPECT_EQ(low.scalar_type(), torch::kBFloat16);
  EXPECT_EQ(net->x_embedder->linear->weight.scalar_type(), torch::kFloat32);
  EXPECT_TRUE(torch::isfinite(low).all().item<bool>());
  const double rel = relative_l2(low, exact);
  std::printf("DiT forward, bf16 autocast vs fp32: relative L2 error %.2e\n", rel);
  // bf16 keeps 8 significant bits (2^-8 = 3.9e-3 per rounding); through two blocks the error
  // stays within a few of those.
  EXPECT_LT(rel, 3e-2);
  EXPECT_GT(rel, 1e-5);  // and it is not secretly float32
}

TEST(WmAmp, Bf16TrainingLearnsLikeFloat32AndSavesFloat32Checkpoints) {
  test::OneThread one;
  torch::Tensor x0, actions;
  action_driven_latents(16, x0, actions, 1);
  WmTrainOptions o;
  o.lr = 2e-3;
  o.grad_clip = 1.0;
  o.warmup_steps = 5;
  auto train = [&](Precision precision, double& before, double& after) {
    torch::manual_seed(0);
    auto trainer = std::make_unique<WmTrainer>(models::ActionDit(amp_dit()), o, torch::kCPU, precision);
    before = trainer->eval_loss(x0, actions, 7);
    for (int64_t step = 0; step < 40; ++step) {
      const auto s = trainer->step(x0, actions, gen(100 + step));
      EXPECT_TRUE(std::isfinite(s.loss) && std::isfinite(s.grad_norm)) << "step " << step;
    }
    after = trainer->eval_loss(x0, actions, 7);
    return trainer;
  };
  double fp32_before = 0, fp32_after = 0, bf16_before = 0, bf16_after = 0;
  train(Precision::kFloat32, fp32_before, fp32_after);
  auto trainer = train(Precision::kBFloat16, bf16_before, bf16_after);
  std::printf("fixed-batch loss after 40 steps: fp32 %.4f -> %.4f, bf16 %.4f -> %.4f\n", fp32_before,
              fp32_after, bf16_before, bf16_after);
  EXPECT_NEAR(bf16_before, fp32_before, 0.05 * fp32_before);  // same init, same noise
  EXPECT_LT(bf16_after, 0.7 * bf16_before);
  EXPECT_LT(bf16_after, 1.25 * fp32_after);

  // Master weights and their gradients stay float32.
  for (const auto& p : trainer->net()->parameters()) {
    EXPECT_EQ(p.scalar_type(), torch::kFloat32);
    if (p.grad().defined()) {
      EXPECT_EQ(p.grad().scalar_type(), torch::kFloat32);
    }
  }

  // The checkpoint holds float32 tensors and loads into a fresh float32 model.
  TempDir dir;
  trainer->save(dir / "ckpt");
  for (const char* file : {"model.safetensors", "trainer_state.safetensors"}) {
    auto f = SafetensorsFile::open(dir / "ckpt" / file);
    for (const auto& key : f.keys()) {
      if (key.rfind("rng.", 0) == 0) continue;  // generator states are bytes
      const auto& dtype = f.info(key).dtype;
      EXPECT_TRUE(dtype == "F32" || dtype == "I64") << file << ": " << key << " is " << dtype;
    }
  }
  const auto loaded = models::load_world_model(dir / "ckpt");
  for (const auto& item : trainer->ema()->named_parameters()) {
    const auto& got = loaded->named_parameters()[item.key()];
    EXPECT_EQ(got.scalar_type(), torch::kFloat32);
    EXPECT_TRUE(got.equal(item.value())) << item.key();
  }
  // And resumes into a bf16 trainer.
  WmTrainer resumed(models::ActionDit(amp_dit()), o, torch::kCPU, Precision::kBFloat16);
  resumed.resume(dir / "ckpt");
  EXPECT_EQ(resumed.steps_done(), 40);
  EXPECT_NEAR(resumed.eval_loss(x0, actions, 7), bf16_after, 1e-6);

  // fp16 would need loss scaling: refused in one line.
  EXPECT_NE(test::error_message([&] {
              WmTrainer(models::ActionDit(amp_dit()), o, torch::kCPU, Precision::kFloat16);
            }).find("loss scaling"),
            std::string::npos);
}

TEST(WmAmp, Bf16RolloutIsCloseToFloat32AndReturnsCpuFrames) {
  test::OneThread one;
  torch::manual_seed(0);
  auto c = amp_dit();
  c.model_channels = 32;
  c.num_blocks = 1;
  c.num_heads = 1;
  models::ActionDit net(c);
  models::WanVae vae(models::WanVaeConfig::tiny());
  // Both share the same modules (CPU: nothing is copied).
  infer::WorldModel fp32(net, vae);
  infer::WorldModel bf16(net, vae, torch::kCPU, Precision::kBFloat16);
  EXPECT_EQ(bf16.precision(), Precision::kBFloat16);
  const auto first = torch::randint(0, 255, {1, 16, 16, 3}, gen(2), torch::kByte);
  const auto actions = torch::rand({1, 12, 384}, gen(3)) * 2 - 1;
  infer::SamplerOptions s;
  s.steps = 3;
  const auto a = fp32.predict_chunk(first, actions, 5, s);
  const auto b = bf16.predict_chunk(first, actions, 5, s);
  EXPECT_EQ(b.sizes(), a.sizes());
  EXPECT_EQ(b.scalar_type(), torch::kUInt8);
  EXPECT_TRUE(b.device().is_cpu());
  EXPECT_FALSE(AutocastGuard::is_enabled(torch::kCPU));  // nothing leaks out of the sampler
  const double mean_diff = (a.to(torch::kFloat32) - b.to(torch::kFloat32)).abs().mean().item<double>();
  std::printf("13-frame chunk, bf16 vs fp32 sampling: mean |difference| %.3f of 255\n", mean_diff);
  EXPECT_LT(mean_diff, 0.5);
  // Frame 0 is decoded from the clean conditioning latent: the same in both (the VAE is float32).
  EXPECT_TRUE(a.select(1, 0).equal(b.select(1, 0)));

  EXPECT_NE(test::error_message([&] {
              infer::WorldModel(net, vae, torch::kCPU, Precision::kFloat16);
            }).find("fp16"),
            std::string::npos);
}

}  // namespace
}  // namespace dojo::train
