#include "train/tokenizer_train.h"

#include <torch/torch.h>

#include <fstream>

#include "core/checkpoint.h"
#include "core/state_dict.h"
#include "data/episode_store.h"
#include "eval/metrics.h"
#include "test_util.h"
#include "train/train_util.h"

#ifdef DOJO_WITH_SIM
#include "sim/generate.h"
#endif

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

using models::model_to_video;
using models::reconstruct;
using models::video_to_model;

// PSNR / SSIM of reconstructions [B, 3, T, H, W] in [-1, 1], with the project's one metric
// implementation (per frame, mean per clip, then over clips) on the uint8 frames.
eval::VideoMetrics clip_metrics(const torch::Tensor& pred, const torch::Tensor& gt) {
  const auto p = model_to_video(pred), g = model_to_video(gt);  // [B, T, H, W, 3]
  std::vector<eval::VideoMetrics> per_clip;
  for (int64_t b = 0; b < p.size(0); ++b) per_clip.push_back(eval::video_metrics(p[b], g[b]));
  return eval::dataset_mean(per_clip);
}

// Capped run of LearnsToReconstructHeldOutClips and the gain it must show (measured margins in
// docs/benchmarks.md).
constexpr int64_t kSteps = 160;
constexpr double kMinGainDb = 4.0;

#ifdef DOJO_WITH_SIM
// A small DojoSim dataset (robot bin task, 32x32): two episodes to train on and a third, never
// seen in training, whose fixed clips measure reconstruction. Random moving squares were a poor
// target here: the tiny model does not generalise across them within a capped run, while DojoSim
// scenes share their structure (table, bins, arm) the way the real data does.
TEST(TokenizerTrainer, LearnsToReconstructHeldOutClips) {
  test::OneThread one_thread;
  test::TempDir tmp;
  sim::GenerateOptions g;
  g.episodes = 3;
  g.frames = 24;
  g.width = g.height = 32;
  g.workers = 1;
  g.val_fraction = 0;
  g.seed = 3;
  sim::generate_dataset(tmp / "data", g);
  const auto store = data::EpisodeStore::open(tmp / "data");
  ASSERT_EQ(store.size(), 3u);
  std::vector<torch::Tensor> train_eps;  // each [3, T, H, W] in [-1, 1]
  for (size_t i = 0; i + 1 < store.size(); ++i)
    train_eps.push_back(video_to_model(store.load(i).frames.unsqueeze(0))[0]);
  const auto held_ep = video_to_model(store.load(store.size() - 1).frames.unsqueeze(0))[0];  // [3, T, H, W]
  constexpr int64_t kFrames = 5;
  // Fixed held-out clips: three windows spread over the unseen episode.
  const auto held_out = torch::stack({held_ep.narrow(1, 0, kFrames), held_ep.narrow(1, 9, kFrames),
                                      held_ep.narrow(1, 18, kFrames)});  // [3, 3, 5, 32, 32]

  torch::manual_seed(0);
  models::WanVae vae(models::WanVaeConfig::tiny());
  models::init_frame_by_frame(vae);  // the recipe: image phase, then clips
  vae->eval();
  const double before = clip_metrics(reconstruct(vae, held_out), held_out).psnr;

  auto o = recommended_tokenizer_options();
  o.steps = kSteps;
  o.warmup_steps = 10;
  o.progress = false;
  // The edge term pays off later than 160 steps of a tiny model at 32x32: here it costs 0.9 dB
  // (+3.67 vs +4.58), at the demo's scale it gains 0.3-0.7 dB (docs/benchmarks.md).
  o.edge_weight = 0;
  // Batch: 4 random 5-frame windows from the training episodes, deterministic per step.
  auto next = [&](int64_t step) {
    auto gen = at::detail::createCPUGenerator(1000 + static_cast<uint64_t>(step));
    std::vector<torch::Tensor> clips;
    for (int i = 0; i < 4; ++i) {
      const auto& ep =
          train_eps[torch::randint(static_cast<int64_t>(train_eps.size()), {1}, gen).item<int64_t>()];
      const int64_t t0 = torch::randint(ep.size(1) - kFrames + 1, {1}, gen).item<int64_t>();
      clips.push_back(ep.narrow(1, t0, kFrames));
    }
    return torch::stack(clips);  // [4, 3, 5, 32, 32]
  };
  const auto result = train_tokenizer(vae, next, o);
  const double after = clip_metrics(reconstruct(vae, held_out), held_out).psnr;
  std::printf("held-out PSNR %.2f -> %.2f dB (+%.2f) in %lld steps, %.1f s; train mse %.4f -> %.4f\n", before,
              after, after - before, static_cast<long long>(result.steps_done), result.seconds,
              result.first_loss, result.last_loss);
  EXPECT_EQ(result.steps_done, kSteps);
  EXPECT_LT(result.last_loss, result.first_loss * 0.5) << result.first_loss << " -> " << result.last_loss;
  EXPECT_GT(after, before + kMinGainDb) << "PSNR before " << before << " after " << after;
  EXPECT_GT(clip_metrics(reconstruct(vae, held_out), held_out).ssim,
            clip_metrics(held_out * 0, held_out).ssim);
}
#endif

// Each clip gets one window, the same for all its frames, and the same seed gives the same windows.
TEST(TokenizerTrainer, RandomCropIsOneWindowPerClip) {
  const auto video = torch::arange(2 * 3 * 5 * 16 * 24, torch::kFloat32).reshape({2, 3, 5, 16, 24});
  const auto a = random_spatial_crop(video, 8, 11);
  ASSERT_EQ(a.sizes(), (std::vector<int64_t>{2, 3, 5, 8, 8}));
  EXPECT_TRUE(torch::equal(a, random_spatial_crop(video, 8, 11)));
  for (int64_t b = 0; b < 2; ++b) {
    // Values encode their position: recover the window's corner from the first element.
    const int64_t first = a[b][0][0][0][0].item<int64_t>() - video[b][0][0][0][0].item<int64_t>();
    const int64_t y = first / 24, x = first % 24;
    EXPECT_TRUE(torch::equal(a[b], video[b].narrow(2, y, 8).narrow(3, x, 8)));
  }
  bool moved = false;  // some seed puts a window elsewhere
  for (uint64_t seed = 0; seed < 8 && !moved; ++seed)
    moved = !torch::equal(random_spatial_crop(video, 8, seed), a);
  EXPECT_TRUE(moved);
  EXPECT_TRUE(torch::equal(random_spatial_crop(video, 0, 1), video));
  EXPECT_TRUE(torch::equal(random_spatial_crop(video, 32, 1), video));
}

TEST(TokenizerTrainer, LearningRateSchedule) {
  TokenizerTrainOptions o;
  o.steps = 110;
  o.lr = 1e-3;
  o.warmup_steps = 10;
  o.cosine = true;
  o.min_lr_fraction = 0.1;
  EXPECT_NEAR(tokenizer_lr(o, 0), 1e-4, 1e-12);     // warm-up starts at lr / warmup
  EXPECT_NEAR(tokenizer_lr(o, 9), 1e-3, 1e-12);     // and reaches lr at its last step
  EXPECT_NEAR(tokenizer_lr(o, 10), 1e-3, 1e-12);    // cosine starts at lr
  EXPECT_NEAR(tokenizer_lr(o, 60), 0.55e-3, 1e-9);  // half way: midpoint of lr and the floor
  EXPECT_NEAR(tokenizer_lr(o, 110), 1e-4, 1e-12);   // floor
  // A time budget half used puts the cosine at least half way, whatever the step.
  EXPECT_NEAR(tokenizer_lr(o, 10, 0.5), 0.55e-3, 1e-9);
  EXPECT_NEAR(tokenizer_lr(o, 10, 1.0), 1e-4, 1e-12);
  EXPECT_NEAR(tokenizer_lr(o, 60, 0.1), 0.55e-3, 1e-9);  // the step count leads: it wins
  EXPECT_NEAR(tokenizer_lr(o, 5, 0.9), 0.6e-3, 1e-12);   // warm-up is by steps only
  o.cosine = false;
  EXPECT_NEAR(tokenizer_lr(o, 100), 1e-3, 1e-12);
}

TEST(TokenizerTrainer, ResumesFromCheckpoint) {
  test::OneThread one_thread;
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
  models::save_tokenizer(dir / "tok", *again);
  auto loaded = models::load_tokenizer(dir / "tok");
  EXPECT_EQ(loaded->config().to_json(), again->config().to_json());
  const auto x = moving_squares(1, 5, 16, 7);
  EXPECT_TRUE(torch::allclose(reconstruct(loaded, x), reconstruct(again, x)));
}

TEST(TokenizerTrainer, ImagePhaseComesFirst) {
  test::OneThread one_thread;
  test::TempDir dir;
  torch::manual_seed(2);
  models::WanVae vae(models::WanVaeConfig::tiny());
  models::init_frame_by_frame(vae);
  TokenizerTrainOptions o;
  o.steps = 4;
  o.progress = false;
  o.image_fraction = 0.5;
  o.loss_curve = dir / "loss.csv";
  std::vector<std::string> calls;
  auto clips = [&](int64_t step) {
    calls.push_back("clips" + std::to_string(step));
    return moving_squares(2, 5, 16, step);
  };
  o.next_image_batch = [&](int64_t step) {
    calls.push_back("images" + std::to_string(step));
    return moving_squares(6, 1, 16, step);  // [6, 3, 1, 16, 16]
  };
  train_tokenizer(vae, clips, o);
  EXPECT_EQ(calls, (std::vector<std::string>{"images0", "images1", "clips2", "clips3"}));
  std::ifstream in(o.loss_curve);
  std::string header, row;
  std::getline(in, header);
  EXPECT_EQ(header, "step,recon,kl,seconds,images");
  std::vector<char> phase;
  while (std::getline(in, row)) phase.push_back(row.back());
  EXPECT_EQ(phase, (std::vector<char>{'1', '1', '0', '0'}));

  // Without an image stream, the image phase trains on every frame of the clip batches.
  o.next_image_batch = nullptr;
  o.loss_curve.clear();
  o.image_fraction = 1.0;
  o.steps = 1;
  models::WanVae other(models::WanVaeConfig::tiny());
  calls.clear();
  EXPECT_EQ(train_tokenizer(other, clips, o).steps_done, 1);
  EXPECT_EQ(calls, std::vector<std::string>{"clips0"});
}

// The loss terms under which one term's share can be checked exactly: L1 of the posterior mean
// (deterministic), no KL, no extra terms.
TokenizerTrainOptions deterministic_l1_terms() {
  TokenizerTrainOptions terms;
  terms.kl_weight = 0;
  terms.sample_posterior = false;
  terms.l1 = true;
  terms.edge_weight = 0;
  terms.hard_pixel_weight = 0;
  return terms;
}

TEST(TokenizerTrainer, EdgeLossSeesEdgesNotOffsets) {
  const auto video = moving_squares(2, 5, 24, 3);  // [2, 3, 5, 24, 24]
  EXPECT_NEAR(edge_l1(video, video + 0.3).item<double>(), 0.0, 1e-6) << "a colour offset has no edges";
  // A square moved by one pixel: its edges no longer line up.
  EXPECT_GT(edge_l1(video.roll(1, 4), video).item<double>(), 0.01);
  // Blurring (a lost edge) is penalised too.
  const auto blurred = (video + video.roll(1, 3) + video.roll(1, 4)) / 3;
  EXPECT_GT(edge_l1(blurred, video).item<double>(), 0.01);
  // The trainer adds it with its weight.
  torch::manual_seed(0);
  models::WanVae vae(models::WanVaeConfig::tiny());
  auto terms = deterministic_l1_terms();
  const auto plain = tokenizer_loss(vae, video, terms);
  terms.edge_weight = 2.0;
  const auto with_edges = tokenizer_loss(vae, video, terms);
  EXPECT_NEAR(with_edges.recon.item<double>() - plain.recon.item<double>(),
              2.0 * edge_l1(vae->decode(vae->encode(video, false).mu, false), video).item<double>(), 1e-4);
}

TEST(TokenizerTrainer, HardPixelLossSeesASmallObjectThatVanished) {
  // A 2x2 "cube" on a flat 16x16 frame, erased in the reconstruction: 4 of 256 pixels.
  auto truth = torch::zeros({1, 3, 1, 16, 16});
  truth.index_put_({0, 0, 0, torch::indexing::Slice(6, 8), torch::indexing::Slice(6, 8)}, 1.5);
  const auto erased = torch::zeros_like(truth);
  const double mean_l1 = torch::l1_loss(erased, truth).item<double>();  // 1.5 * 4 / (3 * 256)
  EXPECT_NEAR(mean_l1, 1.5 * 4 / 768, 1e-6);
  // The worst 4 pixels' channel-mean error: the whole cube, 1.5 / 3 each.
  EXPECT_NEAR(hard_pixel_l1(erased, truth, 4.0 / 256).item<double>(), 0.5, 1e-6);
  // A fraction over the cube's share averages in flawless pixels; under one pixel still takes one.
  EXPECT_NEAR(hard_pixel_l1(erased, truth, 8.0 / 256).item<double>(), 0.25, 1e-6);
  EXPECT_NEAR(hard_pixel_l1(erased, truth, 1e-6).item<double>(), 0.5, 1e-6);
  // Each frame is ranked on its own: a second, perfect frame adds its own worst pixels (zeros).
  const auto two = torch::cat({truth, torch::zeros_like(truth)}, 2);
  EXPECT_NEAR(hard_pixel_l1(torch::zeros_like(two), two, 4.0 / 256).item<double>(), 0.25, 1e-6);
  // Its gradient reaches the vanished pixels only (their red channel, the one in error).
  const auto recon = erased.clone().requires_grad_(true);
  hard_pixel_l1(recon, truth, 4.0 / 256).backward();
  EXPECT_EQ(recon.grad().ne(0).sum().item<int64_t>(), 4);
  EXPECT_EQ(recon.grad().ne(0).logical_and(truth.ne(0)).sum().item<int64_t>(), 4);
  // The trainer adds it with its weight.
  const auto video = moving_squares(2, 5, 24, 3);
  torch::manual_seed(0);
  models::WanVae vae(models::WanVaeConfig::tiny());
  auto terms = deterministic_l1_terms();  // no edge term either
  const auto plain = tokenizer_loss(vae, video, terms);
  terms.hard_pixel_weight = 3.0;
  terms.hard_pixel_fraction = 0.05;
  const auto with_hard = tokenizer_loss(vae, video, terms);
  EXPECT_NEAR(
      with_hard.recon.item<double>() - plain.recon.item<double>(),
      3.0 * hard_pixel_l1(vae->decode(vae->encode(video, false).mu, false), video, 0.05).item<double>(),
      1e-4);
}

TEST(TokenizerTrainer, VideoConversionsRoundTrip) {
  const auto x = moving_squares(2, 5, 16, 3);
  const auto u8 = model_to_video(x);
  EXPECT_EQ(u8.sizes(), (std::vector<int64_t>{2, 5, 16, 16, 3}));
  EXPECT_LT((video_to_model(u8) - x).abs().max().item<double>(), 1.0 / 127.5 + 1e-6);
  const auto m = clip_metrics(x, x);
  EXPECT_EQ(m.psnr, 80.0);  // identical frames: the metric's 1e-8 floor
  EXPECT_NEAR(m.ssim, 1.0, 1e-4);
}

// Checkpoints written before the shared optimizer format named AdamW moments by parameter index
// ("adam.<i>.*"); resuming one restores the moments into the parameters they belong to.
TEST(TokenizerTrainer, ResumesOldIndexNamedOptimizerState) {
  test::OneThread one;
  test::TempDir dir;
  torch::manual_seed(0);
  models::WanVae vae(models::WanVaeConfig::tiny());
  auto o = recommended_tokenizer_options();
  o.steps = 2;
  o.progress = false;
  o.checkpoint_dir = dir / "ckpt";
  auto batch = [](int64_t step) { return moving_squares(1, 5, 16, step); };
  train_tokenizer(vae, batch, o);
  // Rewrite the trainer state the old way, by index in vae->parameters().
  auto ck = Checkpoint::open(o.checkpoint_dir);
  const auto saved = ck.trainer_tensors().tensors(/*copy=*/true);
  const auto named = vae->named_parameters();
  NamedTensors old_format;
  for (const auto& [name, t] : saved) {
    bool renamed = false;
    for (size_t i = 0; i < named.size() && !renamed; ++i) {
      const auto base = "adamw." + named[i].key() + ".";
      if (name.rfind(base, 0) == 0 && name.find('.', base.size()) == std::string::npos) {
        old_format.emplace_back("adam." + std::to_string(i) + "." + name.substr(base.size()), t);
        renamed = true;
      }
    }
    if (!renamed) old_format.emplace_back(name, t);
  }
  CheckpointData data;
  data.config = ck.config();
  data.model = ck.model().tensors(/*copy=*/true);
  data.trainer = TrainerState{ck.step(), nlohmann::json::object(), old_format};
  save_checkpoint(dir / "old", data);

  const auto renamed = named_adamw_state(old_format, *vae);
  std::map<std::string, torch::Tensor> by_name(renamed.begin(), renamed.end());
  std::map<std::string, torch::Tensor> expected(saved.begin(), saved.end());
  ASSERT_EQ(by_name.size(), expected.size());
  for (const auto& [name, t] : expected) {
    ASSERT_TRUE(by_name.count(name)) << name;
    EXPECT_TRUE(by_name[name].equal(t)) << name;
  }
  // Both checkpoints resume to the same next step.
  models::WanVae a(models::WanVaeConfig::tiny()), b(models::WanVaeConfig::tiny());
  o.steps = 3;
  train_tokenizer(a, batch, o);
  o.checkpoint_dir = dir / "old";
  train_tokenizer(b, batch, o);
  const auto sa = state_dict(*a), sb = state_dict(*b);
  ASSERT_EQ(sa.size(), sb.size());
  for (size_t i = 0; i < sa.size(); ++i) EXPECT_TRUE(sa[i].second.equal(sb[i].second)) << sa[i].first;
}

}  // namespace
}  // namespace dojo::train
