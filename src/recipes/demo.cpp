#include "recipes/demo.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <memory>
#include <nlohmann/json.hpp>

#include "core/atomic_file.h"
#include "core/autocast.h"
#include "core/error.h"
#include "core/log.h"
#include "core/runtime.h"
#include "data/clip_loader.h"
#include "data/episode_store.h"
#include "eval/html_report.h"
#include "eval/wm_eval.h"
#include "infer/world_model.h"
#include "models/lam.h"
#include "models/wan_vae.h"
#include "sim/generate.h"
#include "train/lam_train.h"
#include "train/tokenizer_train.h"
#include "train/wm_train.h"

namespace fs = std::filesystem;

namespace dojo::recipes {
namespace {

constexpr int64_t kMaxClips = 192;  // per dataset in the latent cache
// Training stages share the time left after generation, minus a reserve for evaluation, in
// these proportions; each stage's budget is recomputed from the clock when it starts, so a slow
// stage (or a busy machine) shortens the later ones instead of overrunning --minutes.
// The tokenizer gets the largest share: with the 2026-11-22 split (0.12/0.30/0.29/0.29) rollouts sat
// within 0.1 dB of the tokenizer's round trip, so the tokenizer, not the DiT, was the limit
// (docs/benchmarks.md).
constexpr double kLamWeight = 0.10, kTokenizerWeight = 0.40, kPretrainWeight = 0.22, kPosttrainWeight = 0.28;

constexpr double kEvalReserve = 0.10;  // of --minutes

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

std::string fixed(double v, int digits = 2) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.*f", digits, v);
  return buf;
}

}  // namespace

DemoSummary run_demo(const DemoOptions& o) {
  // First, so a CUDA request without CUDA (or fp16, which training rejects) fails before any work.
  const auto device = parse_device(o.device);
  const auto precision = parse_precision(o.precision);
  if (precision == Precision::kFloat16)
    throw UsageError("demo: --precision fp16 cannot train the world model (no loss scaling); use bf16");
  const fs::path out = o.out;
  // Matmul-bound stages (LAM, world model, rollouts) on CPU: one OpenMP thread beside a threaded
  // BLAS unless the caller chose (core/runtime.h says why).
  auto matmul_threads = [&](bool on_cuda) {
    if (on_cuda) return threads();
    return o.matmul_threads > 0 ? o.matmul_threads : matmul_bound_threads();
  };
  fs::create_directories(out);
  const auto start = std::chrono::steady_clock::now();
  const double budget_s = o.minutes * 60.0;
  // Seconds for a stage with weight `w`, given the weights of the stages still to run (w included).
  auto stage_budget = [&](double w, double weights_left) {
    const double left = budget_s * (1 - kEvalReserve) - seconds_since(start);
    return std::max(1.0, left * w / weights_left);
  };
  nlohmann::json report;
  report["device"] = device.str();
  report["precision"] = to_string(precision);
  std::vector<std::pair<std::string, double>> stage_seconds;

  // 1. The world.
  LOG_INFO("[1/7] DojoSim: human and robot episodes into ", out.string());
  auto t0 = std::chrono::steady_clock::now();
  auto generate = [&](const std::string& name, const std::string& embodiment, const std::string& split,
                      int episodes, uint64_t seed, double val_fraction = 0) {
    sim::GenerateOptions g;
    g.val_fraction = val_fraction;
    g.embodiment = embodiment;
    g.split = split;
    g.episodes = episodes;
    g.frames = o.frames;
    g.seed = seed;
    g.workers = o.workers;
    const auto s = sim::generate_dataset(out / name, g);
    report["data"][name] = {{"episodes", episodes}, {"generated", s.generated}, {"seconds", s.seconds}};
    if (!std::isnan(s.mean_success)) report["data"][name]["bin_success"] = s.mean_success;
  };
  generate("human", "human", "train", o.episodes, o.seed);
  // The last eval_episodes robot episodes form the held-out "val" split.
  generate("robot", "robot", "train", o.episodes + o.eval_episodes, o.seed + 1,
           static_cast<double>(o.eval_episodes) / (o.episodes + o.eval_episodes));
  generate("robot_ood_objects", "robot", "ood-objects", o.eval_episodes, o.seed + 2);
  generate("robot_counterfactual", "robot", "counterfactual", o.eval_episodes, o.seed + 3);
  data::write_preview_video(data::EpisodeStore::open(out / "human"), out / "preview_human.mp4", 4, 2);
  data::write_preview_video(data::EpisodeStore::open(out / "robot"), out / "preview_robot.mp4", 4, 2);
  stage_seconds.emplace_back("generate DojoSim data", seconds_since(t0));

  // 2. Latent action model on human and robot video (no actions used).
  const double weights = kLamWeight + kTokenizerWeight + kPretrainWeight + kPosttrainWeight;
  const double lam_s = stage_budget(kLamWeight, weights);
  LOG_INFO("[2/7] LAM: latent actions from video alone (", fixed(lam_s / 60, 1), " min)");
  t0 = std::chrono::steady_clock::now();
  train::LamTrainJob lam;
  lam.datasets = {{out / "human", 1.0}, {out / "robot", 1.0}};
  lam.out = out / "lam";
  lam.model = models::LamConfig::small();
  lam.options.lr = 3e-4;  // small model, short run: the released 2.5e-5 is for 700 M parameters
  lam.batch_size = 8;
  lam.steps = 1000000;
  lam.save_every = 100;
  lam.seed = o.seed;
  lam.time_budget_s = lam_s;
  const auto lam_stats = [&] {
    // The LAM trains on the CPU. The tokenizer's oneDNN convolutions, next, use every thread.
    ScopedThreads matmul_bound(matmul_threads(/*on_cuda=*/false));
    return train::run_lam_training(lam);
  }();
  report["lam"] = {{"mse", lam_stats.mse}, {"psnr", lam_stats.psnr}};
  stage_seconds.emplace_back("train LAM", seconds_since(t0));

  // 3. Tokenizer.
  const double tok_s = stage_budget(kTokenizerWeight, weights - kLamWeight);
  LOG_INFO("[3/7] tokenizer: Wan2.1-architecture VAE (", fixed(tok_s / 60, 1), " min)");
  t0 = std::chrono::steady_clock::now();
  {
    models::WanVaeConfig cfg;
    cfg.dim = 16;
    models::WanVae vae(cfg);
    models::init_frame_by_frame(vae);  // image phase first; a resumed run loads over this
    data::ClipConfig clip;
    // 9 frames = 3 latent frames: the first chunk and one steady-state chunk that decodes from
    // the causal caches of the one before. Trained on 5 frames only, latent frames >= 2 of the
    // world model's 13-frame clips decoded to flat colour (measured: 13-frame PSNR 17.2 dB vs
    // 21.0 dB on 5 frames, later frames washed out).
    clip.num_frames = 9;
    clip.strides = {1, 2};
    clip.height = clip.width = 64;
    const auto batches = train::tokenizer_batches({{out / "human", "all"}, {out / "robot", "train"}}, clip,
                                                  /*clip_batch=*/4, /*image_batch=*/8, /*workers=*/1, o.seed);
    // Batches of 8 frames: as good as 16 at equal time on this data (more, noisier steps).
    train::TokenizerTrainOptions t = train::recommended_tokenizer_options();
    t.warmup_steps = 20;
    t.steps = 1000000;
    t.save_every = 100;
    t.checkpoint_dir = out / "tokenizer" / "checkpoint";
    t.loss_curve = out / "tokenizer" / "loss.csv";
    t.stats_batches = 8;
    t.next_image_batch = batches.images;
    t.time_budget_s = tok_s;
    fs::create_directories(out / "tokenizer");
    torch::manual_seed(o.seed);
    const auto r = train::train_tokenizer(vae, batches.clips, t);
    report["tokenizer"] = {
        {"steps", r.steps_done}, {"recon_first", r.first_loss}, {"recon_last", r.last_loss}};
  }
  stage_seconds.emplace_back("train tokenizer", seconds_since(t0));
  const fs::path tokenizer = out / "tokenizer" / "checkpoint";

  // 4-5. World model: pretrain on human video with latent actions, post-train on robot actions.
  auto wm_job = [&](train::WmStage stage, const fs::path& dataset, const std::string& split,
                    train::ActionMode mode, const fs::path& dir, double seconds) {
    train::WmTrainJob job;
    job.stage = stage;
    train::LatentCacheSpec spec;
    spec.dataset = dataset;
    spec.split = split;
    spec.tokenizer = tokenizer;
    spec.lam = out / "lam" / "checkpoint";
    spec.mode = mode;
    // Encoding is the slow part of caching (one 13-frame clip at a time, as the release does):
    // windows every 4 frames at strides 1 and 2, at most kMaxClips of them, evenly spread.
    spec.hop = 4;
    spec.max_clips = kMaxClips;
    job.data = {spec};
    job.out = dir;
    if (stage == train::WmStage::kPosttrain) job.init = out / "wm_pretrain" / "checkpoint";
    job.model = models::DitConfig::small();
    job.options.lr = 3e-4;  // small network, few thousand steps
    job.options.grad_clip = 1.0;
    job.options.warmup_steps = 50;
    job.batch_size = 8;
    job.steps = 1000000;
    job.time_budget_s = seconds;
    job.save_every = 100;
    job.seed = o.seed;
    job.device = device;
    job.precision = precision;
    ScopedThreads matmul_bound(matmul_threads(device.is_cuda()));
    return train::run_wm_training(job);
  };
  const double pre_s = stage_budget(kPretrainWeight, kPretrainWeight + kPosttrainWeight);
  LOG_INFO("[4/7] world model pretraining on human video with latent actions (", fixed(pre_s / 60, 1),
           " min, latent caching included)");
  t0 = std::chrono::steady_clock::now();
  const auto pre = wm_job(train::WmStage::kPretrain, out / "human", "all", train::ActionMode::kLatent,
                          out / "wm_pretrain", pre_s);
  report["wm_pretrain"] = {{"steps", pre.steps},
                           {"loss_first", pre.first_loss},
                           {"loss_last", pre.last_loss},
                           {"clips_per_second", pre.clips_per_second}};
  stage_seconds.emplace_back("world model pretrain", seconds_since(t0));

  const double post_s = stage_budget(kPosttrainWeight, kPosttrainWeight);
  LOG_INFO("[5/7] world model post-training on robot actions (", fixed(post_s / 60, 1),
           " min, latent caching included)");
  t0 = std::chrono::steady_clock::now();
  const auto post = wm_job(train::WmStage::kPosttrain, out / "robot", "train", train::ActionMode::kDataset,
                           out / "wm_posttrain", post_s);
  report["wm_posttrain"] = {{"steps", post.steps},
                            {"loss_first", post.first_loss},
                            {"loss_last", post.last_loss},
                            {"clips_per_second", post.clips_per_second}};
  stage_seconds.emplace_back("world model post-train", seconds_since(t0));

  // 6. Rollouts and evaluation.
  LOG_INFO(
      "[6/7] rollouts: 49 frames (4 chunks, 3 resets) on held-out and out-of-distribution robot episodes");
  t0 = std::chrono::steady_clock::now();
  auto model = infer::WorldModel::load(out / "wm_posttrain" / "checkpoint", tokenizer, device, precision);
  eval::WmEvalOptions eo;
  eo.max_episodes = o.eval_episodes;
  eo.sampler.steps = o.sampler_steps;
  eo.seed = o.seed;
  eo.video_dir = out / "rollouts";
  eo.videos = 2;
  std::vector<eval::WmEvalResult> results;
  {
    // DiT sampling is matmul-bound: 31.0 generated frames/s with one OpenMP thread, 12.6 with two.
    ScopedThreads matmul_bound(matmul_threads(device.is_cuda()));
    results.push_back(eval::evaluate_world_model(model, out / "robot", "val", eo));
    results.push_back(eval::evaluate_world_model(model, out / "robot_ood_objects", "all", eo));
    results.back().split = "ood-objects";
    results.push_back(eval::evaluate_world_model(model, out / "robot_counterfactual", "all", eo));
    results.back().split = "counterfactual";
  }
  nlohmann::json evals = nlohmann::json::array();
  for (const auto& r : results) evals.push_back(r.to_json());
  report["eval"] = evals;
  write_file_atomic(out / "eval.md", eval::markdown_table(results));
  stage_seconds.emplace_back("rollouts + evaluation", seconds_since(t0));

  // 7. Report.
  LOG_INFO("[7/7] report: ", (out / "report.html").string());
  eval::HtmlReport html("DreamDojo.cpp demo on DojoSim");
  html.paragraph(
      "Everything below was made by `dojo demo` on this machine: DojoSim generated human and robot episodes; "
      "a "
      "small latent action model learned actions from video alone; a small Wan2.1-architecture tokenizer "
      "learned "
      "the latent space; the action-conditioned DiT was pretrained on human video with latent actions and "
      "post-trained on robot actions; it then rolled out 49-frame videos (4 chunks of 12 actions, 3 "
      "autoregressive "
      "resets) from the first frame and the recorded actions of episodes it never saw.");
  html.heading("Rollouts vs ground truth");
  html.paragraph(
      "PSNR/SSIM per frame (piq conventions), mean per video, then over videos. The copy-frame-0 baseline "
      "repeats the real conditioning frame: a model that ignores the actions scores about that. The "
      "tokenizer round trip (ground truth encoded and decoded) is the ceiling for any rollout decoded by "
      "this tokenizer.");
  std::vector<std::vector<std::string>> rows;
  for (const auto& r : results)
    rows.push_back({r.split, std::to_string(r.videos.size()), fixed(r.psnr), fixed(r.copy_psnr),
                    fixed(r.recon_psnr), fixed(r.ssim, 3), fixed(r.copy_ssim, 3),
                    fixed(r.frames_per_second, 1)});
  html.table({"split", "videos", "PSNR (dB)", "copy-frame PSNR", "tokenizer round-trip PSNR", "SSIM",
              "copy-frame SSIM", "frames/s"},
             rows);
  for (const auto& r : results)
    for (const auto& v : r.videos)
      if (!v.video.empty())
        html.video(v.video, r.split + " / " + v.episode +
                                ": ground truth | world model | copy frame 0 | tokenizer round trip (PSNR " +
                                fixed(v.psnr) + " vs " + fixed(v.copy_psnr) + ")");
  html.heading("Training");
  html.line_chart(
      "World model: flow-matching loss",
      {eval::read_csv_series(out / "wm_pretrain" / "loss.csv", "step", "loss", "pretrain (human, latent)"),
       eval::read_csv_series(out / "wm_posttrain" / "loss.csv", "step", "loss", "post-train (robot)")},
      "step", "loss", true, 20);
  html.line_chart("Tokenizer: reconstruction MSE",
                  {eval::read_csv_series(out / "tokenizer" / "loss.csv", "step", "recon", "recon")}, "step",
                  "mse", true, 20);
  html.line_chart("LAM: reconstruction PSNR",
                  {eval::read_csv_series(out / "lam" / "loss.csv", "step", "psnr", "psnr")}, "step", "dB",
                  false, 20);
  html.heading("Data");
  html.video(out / "preview_human.mp4", "human episodes (no actions)");
  html.video(out / "preview_robot.mp4", "robot episodes");
  html.heading("Time per stage");
  std::vector<std::vector<std::string>> trows;
  for (const auto& [name, s] : stage_seconds) trows.push_back({name, fixed(s, 1) + " s"});
  trows.push_back({"total", fixed(seconds_since(start), 1) + " s"});
  html.table({"stage", "time"}, trows);
  html.write(out / "report.html");

  report["stage_seconds"] = nlohmann::json::object();
  for (const auto& [name, s] : stage_seconds) report["stage_seconds"][name] = s;
  report["seconds"] = seconds_since(start);
  write_file_atomic(out / "demo.json", report.dump(2) + "\n");

  DemoSummary summary;
  summary.report = out / "report.html";
  summary.seconds = report["seconds"].get<double>();
  summary.eval_table = eval::markdown_table(results);
  return summary;
}

}  // namespace dojo::recipes
