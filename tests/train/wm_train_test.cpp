#include "train/wm_train.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <ATen/CPUGeneratorImpl.h>

#include "core/safetensors.h"
#include "core/state_dict.h"
#include "data/clip_loader.h"
#include "data/episode_store.h"
#include "diffusion/samplers.h"
#include "models/lam.h"
#include "models/wan_vae.h"
#include "synthetic_data.h"
#include "test_util.h"
#include "train/lam_train.h"
#include "train/tokenizer_train.h"
#include "wm_test_fixtures.h"

namespace dojo::train {
namespace {

using test::SyntheticOptions;
using test::TempDir;
using test::write_synthetic_dataset;

using test_fixtures::action_driven_latents;
using test_fixtures::gen;
using test_fixtures::tiny_dit;

TEST(WmTrain, ParsesModesAndStagesWithClearErrors) {
  EXPECT_EQ(parse_action_mode("latent"), ActionMode::kLatent);
  EXPECT_EQ(parse_action_mode("ground-truth"), ActionMode::kGroundTruth);
  EXPECT_EQ(to_string(ActionMode::kNone), "none");
  EXPECT_NE(test::error_message([] { parse_action_mode("lat"); }).find("'lat'"), std::string::npos);
  EXPECT_EQ(parse_wm_stage("posttrain"), WmStage::kPosttrain);
  EXPECT_NE(test::error_message([] { parse_wm_stage("finetune"); }).find("finetune"), std::string::npos);
}

TEST(WmTrain, OptionsRoundTripThroughJson) {
  WmTrainOptions o;
  o.lr = 3e-4;
  o.flow.temporal_axis = diffusion::TemporalAxis::kChannel;
  o.flow.temporal_weight = 0.25;
  const auto back = WmTrainOptions::from_json(o.to_json());
  EXPECT_EQ(back.lr, 3e-4);
  EXPECT_EQ(back.flow.temporal_axis, diffusion::TemporalAxis::kChannel);
  EXPECT_EQ(back.flow.temporal_weight, 0.25);
  auto bad = o.to_json();
  bad["flow"]["temporal_axis"] = "space";
  EXPECT_NE(test::error_message([&] { WmTrainOptions::from_json(bad); }).find("temporal_axis"),
            std::string::npos);
}

TEST(WmTrain, LearnsActionDrivenLatentsAndBeatsCopyingTheFirstFrame) {
  test::OneThread one;
  torch::manual_seed(0);
  torch::Tensor x0, actions;
  action_driven_latents(64, x0, actions, 1);
  WmTrainOptions o;
  o.lr = 2e-3;
  o.grad_clip = 1.0;
  o.warmup_steps = 10;
  WmTrainer trainer(models::ActionDit(tiny_dit()), o);
  const auto probe_x0 = x0.narrow(0, 0, 16), probe_a = actions.narrow(0, 0, 16);
  const double before = trainer.eval_loss(probe_x0, probe_a, 7);
  for (int64_t step = 0; step < 150; ++step) {
    auto g = gen(100 + step);
    const auto idx = torch::randint(64, {16}, g, torch::kLong);
    trainer.step(x0.index_select(0, idx), actions.index_select(0, idx), g);
  }
  const double after = trainer.eval_loss(probe_x0, probe_a, 7);
  EXPECT_LT(after, 0.5 * before) << "fixed-batch flow loss " << before << " -> " << after;

  // Sampled futures (EMA net, 10 UniPC steps) land closer to the true frames than frame 0 does.
  torch::NoGradGuard no_grad;
  auto& net = trainer.ema();
  auto mask = torch::zeros({16, 1, 4, 4, 4});
  mask.select(2, 0).fill_(1);
  const auto noise = torch::randn(probe_x0.sizes(), gen(3));
  const diffusion::VelocityFn v = [&](const torch::Tensor& x, double, int64_t t) {
    models::DitInputs in;
    in.timesteps = torch::full({16, 1}, static_cast<double>(t));
    in.condition_mask = mask;
    in.actions = probe_a;
    return models::denoise_velocity(*net, in, x, probe_x0, noise, mask);
  };
  const auto sample =
      diffusion::sample_flow(v, noise, diffusion::flow_sigma_schedule(10, 5.0), diffusion::Solver::kUniPC);
  const auto future = probe_x0.narrow(2, 1, 3);
  const double model_mse = (sample.narrow(2, 1, 3) - future).pow(2).mean().item<double>();
  const double copy_mse = (probe_x0.narrow(2, 0, 1).expand_as(future) - future).pow(2).mean().item<double>();
  // The conditioning frame stays on its interpolation path up to the grid's start at
  // sigma = 0.999 rather than 1 (the sampler starts from pure noise): within ~1e-3 of gt.
  EXPECT_LT((sample.narrow(2, 0, 1) - probe_x0.narrow(2, 0, 1)).abs().max().item<double>(), 5e-3);
  std::printf("fixed-batch loss %.4f -> %.4f; future-latent MSE model %.4f vs copy-frame-0 %.4f\n", before,
              after, model_mse, copy_mse);
  EXPECT_LT(model_mse, 0.5 * copy_mse) << "model " << model_mse << " vs copy-frame-0 " << copy_mse;
}

TEST(WmTrain, ResumeContinuesExactly) {
  test::OneThread one;
  torch::Tensor x0, actions;
  action_driven_latents(8, x0, actions, 2);
  WmTrainOptions o;
  o.lr = 1e-3;
  o.warmup_steps = 2;
  auto run_steps = [&](WmTrainer& t, int64_t from, int64_t to) {
    for (int64_t s = from; s < to; ++s) t.step(x0, actions, gen(50 + s));
  };
  torch::manual_seed(5);
  WmTrainer straight(models::ActionDit(tiny_dit()), o);
  run_steps(straight, 0, 4);

  TempDir dir;
  torch::manual_seed(5);
  {
    WmTrainer first(models::ActionDit(tiny_dit()), o);
    run_steps(first, 0, 2);
    first.save(dir / "ckpt");
  }
  torch::manual_seed(99);  // a different fresh init: everything must come from the checkpoint
  WmTrainer resumed(models::ActionDit(tiny_dit()), o);
  resumed.resume(dir / "ckpt");
  EXPECT_EQ(resumed.steps_done(), 2);
  run_steps(resumed, 2, 4);
  const auto want = state_dict(*straight.net()), got = state_dict(*resumed.net());
  ASSERT_EQ(want.size(), got.size());
  for (size_t i = 0; i < want.size(); ++i) EXPECT_TRUE(want[i].second.equal(got[i].second)) << want[i].first;
  for (const auto& item : straight.ema()->named_parameters())
    EXPECT_TRUE(item.value().equal(resumed.ema()->named_parameters()[item.key()])) << "ema " << item.key();

  // The inference checkpoint is the EMA network under the released "net." names.
  const auto loaded = models::load_world_model(dir / "ckpt");
  EXPECT_FALSE(loaded->is_training());
  auto file = SafetensorsFile::open(dir / "ckpt" / "model.safetensors");
  EXPECT_TRUE(file.contains("net.blocks.0.self_attn.q_proj.weight"));
  EXPECT_TRUE(file.contains("net.action_embedder_B_D.fc1.weight"));
}

// Shared by the latent-cache tests: a tiny human dataset, a random tokenizer and a random LAM.
struct CacheFixture {
  TempDir dir;
  CacheFixture() {
    SyntheticOptions g;
    g.embodiment = "human";
    g.episodes = 2;
    g.frames = 20;
    write_synthetic_dataset(dir / "human", g);
    torch::manual_seed(0);
    models::WanVae vae(models::WanVaeConfig::tiny());
    models::save_tokenizer(dir / "tok", *vae);
    LamTrainer lam(models::LatentActionModel(models::LamConfig::tiny()), LamTrainOptions{});
    lam.save(dir / "lam");
  }
  LatentCacheSpec spec(ActionMode mode) const {
    LatentCacheSpec s;
    s.dataset = dir / "human";
    s.split = "all";
    s.tokenizer = dir / "tok";
    s.lam = dir / "lam";
    s.mode = mode;
    s.strides = {1};
    s.hop = 3;
    return s;
  }
};

TEST(WmTrain, LatentCacheHoldsTokenizerLatentsAndLamActions) {
  test::OneThread one;
  CacheFixture f;
  const auto spec = f.spec(ActionMode::kLatent);
  const auto clips = load_or_build_latent_clips(spec, f.dir / "cache.safetensors");
  // 20-frame episodes, 14 steps per 13-frame clip at stride 1 (starts 0..6), hop 3 -> starts
  // 0, 3, 6 in each episode.
  ASSERT_EQ(clips.size(), 6);
  EXPECT_EQ(clips.latents.sizes(), (std::vector<int64_t>{6, 16, 4, 4, 4}));
  EXPECT_EQ(clips.actions.sizes(), (std::vector<int64_t>{6, 12, 384}));

  // Clip 1 is episode 0 from frame 3: recompute it by hand.
  auto store = data::EpisodeStore::open(f.dir / "human");
  data::ClipConfig cc;
  cc.strides = {1};
  cc.height = cc.width = 32;
  data::ClipDataset ds(store, cc, "all");
  const auto clip = ds.read(0, data::make_window(3, 1, 13));
  auto vae = models::load_tokenizer(f.dir / "tok");
  auto lam = models::load_lam(f.dir / "lam");
  torch::NoGradGuard no_grad;
  const auto z = vae->encode_latents(models::video_to_model(clip.video.unsqueeze(0)));
  EXPECT_LT((clips.latents[1] - z[0]).abs().max().item<double>(), 1e-5);
  const auto lam_z = models::lam_encode_episode(lam, clip.video);  // [12, 32]
  EXPECT_LT((clips.actions[1].slice(1, 352, 384) - lam_z).abs().max().item<double>(), 1e-5);
  EXPECT_EQ(clips.actions[1].slice(1, 0, 352).abs().sum().item<double>(), 0.0);

  // A second call reads the file; a different spec rebuilds it.
  const auto mtime = std::filesystem::last_write_time(f.dir / "cache.safetensors");
  const auto again = load_or_build_latent_clips(spec, f.dir / "cache.safetensors");
  EXPECT_TRUE(again.latents.equal(clips.latents));
  EXPECT_EQ(std::filesystem::last_write_time(f.dir / "cache.safetensors"), mtime);
  auto none = f.spec(ActionMode::kNone);
  const auto zero = load_or_build_latent_clips(none, f.dir / "cache.safetensors");
  EXPECT_EQ(zero.actions.abs().sum().item<double>(), 0.0);
  EXPECT_TRUE(zero.latents.equal(clips.latents));

  // Ground-truth motion: chunk-relative hand motion, scaled to a peak of 1 per dimension.
  const auto gt = load_or_build_latent_clips(f.spec(ActionMode::kGroundTruth), f.dir / "gt.safetensors");
  const auto slot = gt.actions.slice(2, 352, 358);  // the hand's 6 motion dimensions
  EXPECT_NEAR(slot.abs().amax({0, 1}).max().item<double>(), 1.0, 1e-6);
  EXPECT_EQ(gt.actions.slice(2, 358, 384).abs().sum().item<double>(), 0.0);
  // By hand: row j of a clip is motion[j + 1] - motion[first frame of j's chunk].
  std::vector<torch::Tensor> raw;
  for (size_t ep : {0, 1})
    for (int64_t start : {0, 3, 6}) {
      const auto m = ds.read(ep, data::make_window(start, 1, 13)).hidden_motion;  // [13, 6]
      auto rows = torch::empty({12, m.size(1)});
      for (int64_t j = 0; j < 12; ++j) rows[j] = m[j + 1] - m[(j / 4) * 4];
      raw.push_back(rows);
    }
  const auto by_hand = torch::stack(raw);  // [6, 12, 6]
  const auto expected = by_hand / by_hand.abs().amax({0, 1}).clamp_min(1e-6);
  EXPECT_LT((slot - expected).abs().max().item<double>(), 1e-5);
}

TEST(WmTrain, LatentActionsWithoutLamFailClearly) {
  CacheFixture f;
  auto spec = f.spec(ActionMode::kLatent);
  spec.lam.clear();
  EXPECT_NE(
      test::error_message([&] { load_or_build_latent_clips(spec, f.dir / "c.safetensors"); }).find("LAM"),
      std::string::npos);
  spec = f.spec(ActionMode::kDataset);
  spec.tokenizer = f.dir / "nope";
  EXPECT_NE(
      test::error_message([&] { load_or_build_latent_clips(spec, f.dir / "c.safetensors"); }).find("nope"),
      std::string::npos);
}

}  // namespace
}  // namespace dojo::train
