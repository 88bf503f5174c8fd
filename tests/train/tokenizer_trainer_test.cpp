#include "train/tokenizer_trainer.h"

#include <torch/torch.h>

#include "core/checkpoint.h"
#include "test_util.h"

namespace dojo::train {
namespace {

// A tiny generated dataset: coloured squares moving over a coloured background,
// [B, 3, T, H, W] in [-1, 1]. Different seeds give disjoint (held-out) clips.
torch::Tensor moving_squares(int64_t batch, int64_t frames, int64_t size, uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(seed);
  auto video = torch::empty({batch, 3, frames, size, size});
  for (int64_t b = 0; b < batch; ++b) {
    const auto bg = torch::rand({3}, gen) * 2 - 1;
    const auto fg = torch::rand({3}, gen) * 2 - 1;
    const int64_t side = size / 3;
    const auto pos = torch::rand({2}, gen) * (size - side);
    const auto vel = (torch::rand({2}, gen) - 0.5) * 4;
    for (int64_t t = 0; t < frames; ++t) {
      video[b].select(1, t).copy_(bg.view({3, 1, 1}).expand({3, size, size}));
      auto p = pos + vel * static_cast<double>(t);
      const int64_t y = std::clamp<int64_t>(p[0].item<double>(), 0, size - side);
      const int64_t x = std::clamp<int64_t>(p[1].item<double>(), 0, size - side);
      video[b]
          .select(1, t)
          .narrow(1, y, side)
          .narrow(2, x, side)
          .copy_(fg.view({3, 1, 1}).expand({3, side, side}));
    }
  }
  return video;
}

// Tiny tensors: one thread avoids OpenMP synchronisation that dominates (and, on a loaded
// machine, multiplies) the run time.
struct OneThread {
  int saved = torch::get_num_threads();
  OneThread() { torch::set_num_threads(1); }
  ~OneThread() { torch::set_num_threads(saved); }
};

TEST(TokenizerTrainer, DISABLED_LearnsToReconstructHeldOutClips) {
  OneThread one_thread;
  torch::manual_seed(0);
  models::WanVae vae(models::WanVaeConfig::tiny());
  vae->eval();
  const auto held_out = moving_squares(4, 5, 16, 999);
  const double before = psnr(reconstruct(vae, held_out), held_out);

  TokenizerTrainOptions o;
  o.steps = 150;
  o.lr = 2e-3;
  o.progress = false;
  const auto result = train_tokenizer(
      vae, [](int64_t step) { return moving_squares(4, 5, 32, step); }, o);
  const double after = psnr(reconstruct(vae, held_out), held_out);
  EXPECT_EQ(result.steps_done, 200);
  EXPECT_LT(result.last_loss, result.first_loss * 0.5) << result.first_loss << " -> " << result.last_loss;
  std::printf("held-out PSNR %.2f -> %.2f dB in %.1f s\n", before, after, result.seconds);
  EXPECT_GT(after, before + 5.0) << "PSNR before " << before << " after " << after;
  EXPECT_GT(ssim(reconstruct(vae, held_out), held_out), ssim(held_out * 0, held_out));
}

TEST(TokenizerTrainer, ResumesFromCheckpoint) {
  OneThread one_thread;
  test::TempDir dir;
  torch::manual_seed(1);
  models::WanVae vae(models::WanVaeConfig::tiny());
  TokenizerTrainOptions o;
  o.steps = 2;
  o.progress = false;
  o.checkpoint_dir = dir / "ckpt";
  auto batch = [](int64_t step) { return moving_squares(1, 5, 16, step); };
  train_tokenizer(vae, batch, o);
  EXPECT_EQ(Checkpoint::open(o.checkpoint_dir).step(), 2);

  models::WanVae again(models::WanVaeConfig::tiny());
  o.steps = 3;
  const auto r = train_tokenizer(again, batch, o);
  EXPECT_EQ(r.steps_done, 3);
  EXPECT_EQ(Checkpoint::open(o.checkpoint_dir).step(), 3);

  // Inference checkpoint round trip keeps config and weights.
  save_tokenizer(dir / "tok", again);
  auto loaded = load_tokenizer(dir / "tok");
  EXPECT_EQ(loaded->config().to_json(), again->config().to_json());
  const auto x = moving_squares(1, 5, 16, 7);
  EXPECT_TRUE(torch::allclose(reconstruct(loaded, x), reconstruct(again, x)));
}

TEST(TokenizerTrainer, MetricsBehave) {
  const auto x = moving_squares(2, 5, 16, 3);
  EXPECT_GT(psnr(x, x), 100.0);
  EXPECT_NEAR(ssim(x, x), 1.0, 1e-4);
  const auto noisy = (x + 0.2 * torch::randn_like(x)).clamp(-1, 1);
  EXPECT_LT(psnr(noisy, x), 30.0);
  EXPECT_LT(ssim(noisy, x), 0.99);
  const auto u8 = model_to_video(x);
  EXPECT_EQ(u8.sizes(), (std::vector<int64_t>{2, 5, 16, 16, 3}));
  EXPECT_LT((video_to_model(u8) - x).abs().max().item<double>(), 1.0 / 127.5 + 1e-6);
}

}  // namespace
}  // namespace dojo::train
