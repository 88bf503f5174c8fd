#include "train/tokenizer_train.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/state_dict.h"
#include "data/clip_loader.h"
#include "data/episode_store.h"
#include "train/data_parallel.h"
#include "train/train_loop.h"
#include "train/train_util.h"

namespace dojo::train {

using models::WanVae;

TokenizerTrainOptions recommended_tokenizer_options() {
  TokenizerTrainOptions o;
  o.lr = 2e-3;
  o.warmup_steps = 50;
  o.cosine = true;
  o.sample_posterior = false;
  o.l1 = true;
  o.kl_weight = 1e-6;
  o.image_fraction = 0.85;
  o.edge_weight = 1.0;
  return o;
}

double tokenizer_lr(const TokenizerTrainOptions& o, int64_t step, double budget_fraction) {
  if (o.warmup_steps > 0 && step < o.warmup_steps)
    return o.lr * static_cast<double>(step + 1) / static_cast<double>(o.warmup_steps);
  if (!o.cosine) return o.lr;
  const int64_t decay_steps = std::max<int64_t>(1, o.steps - o.warmup_steps);
  const double progress =
      std::min(1.0, std::max(static_cast<double>(step - o.warmup_steps) / static_cast<double>(decay_steps),
                             budget_fraction));
  const double floor = o.min_lr_fraction * o.lr;
  return floor + (o.lr - floor) * 0.5 * (1.0 + std::cos(std::acos(-1.0) * progress));
}

torch::Tensor random_spatial_crop(const torch::Tensor& video, int64_t size, uint64_t seed) {
  const int64_t H = video.size(3), W = video.size(4);
  if (size <= 0 || (size >= H && size >= W)) return video;
  const int64_t ch = std::min(size, H), cw = std::min(size, W);
  std::mt19937_64 rng(seed * 0x9E3779B97F4A7C15ull + 0x5851F42D4C957F2Dull);
  std::vector<torch::Tensor> clips;
  for (int64_t b = 0; b < video.size(0); ++b) {
    const auto y = static_cast<int64_t>(rng() % static_cast<uint64_t>(H - ch + 1));
    const auto x = static_cast<int64_t>(rng() % static_cast<uint64_t>(W - cw + 1));
    clips.push_back(video[b].narrow(2, y, ch).narrow(3, x, cw));  // [C, T, ch, cw]
  }
  return torch::stack(clips).contiguous();  // [B, C, T, ch, cw]
}

torch::Tensor edge_l1(const torch::Tensor& a, const torch::Tensor& b) {
  const auto d = a - b;  // [B, C, T, H, W]
  const auto along_h = (d.narrow(3, 1, d.size(3) - 1) - d.narrow(3, 0, d.size(3) - 1)).abs().mean();
  const auto along_w = (d.narrow(4, 1, d.size(4) - 1) - d.narrow(4, 0, d.size(4) - 1)).abs().mean();
  return along_h + along_w;
}

torch::Tensor hard_pixel_l1(const torch::Tensor& a, const torch::Tensor& b, double fraction) {
  const auto error = (a - b).abs().mean(1);                                   // [B, T, H, W]
  const auto per_frame = error.reshape({error.size(0) * error.size(1), -1});  // [B*T, H*W]
  const auto k = std::clamp<int64_t>(static_cast<int64_t>(fraction * static_cast<double>(per_frame.size(1))),
                                     1, per_frame.size(1));
  return std::get<0>(per_frame.topk(k, /*dim=*/1)).mean();
}

TokenizerLoss tokenizer_loss(WanVae& vae, const torch::Tensor& video, const TokenizerTrainOptions& o) {
  auto enc = vae->encode(video, /*chunked=*/false);     // mu, log_var: [B, z, T', h, w]
  const auto log_var = enc.log_var.clamp(-30.0, 20.0);  // the release's clamp
  auto z = enc.mu;
  if (o.sample_posterior) z = z + torch::exp(0.5 * log_var) * torch::randn_like(z);
  const auto recon = vae->decode(z, /*chunked=*/false);  // [B, 3, T, H, W]
  TokenizerLoss loss;
  loss.mse = torch::mse_loss(recon, video);
  // L1 penalises small errors more than MSE does, which sharpens edges late in training.
  loss.recon = o.l1 ? torch::l1_loss(recon, video) : loss.mse;
  if (o.edge_weight > 0) loss.recon = loss.recon + o.edge_weight * edge_l1(recon, video);
  if (o.hard_pixel_weight > 0)
    loss.recon = loss.recon + o.hard_pixel_weight * hard_pixel_l1(recon, video, o.hard_pixel_fraction);
  // KL(N(mu, sigma) || N(0, 1)), mean over latent elements.
  loss.kl = 0.5 * (enc.mu.pow(2) + log_var.exp() - 1.0 - log_var).mean();
  loss.total = loss.recon + o.kl_weight * loss.kl;
  return loss;
}

namespace {

void save_training_checkpoint(const std::filesystem::path& dir, WanVae& vae, const torch::optim::AdamW& opt,
                              int64_t step, const nlohmann::json& extra) {
  CheckpointData data = models::tokenizer_checkpoint(*vae);
  TrainerState t;
  t.step = step;
  t.extra = extra;
  t.tensors = adamw_state(opt, *vae);
  for (auto& r : capture_rng_state()) t.tensors.push_back(r);
  data.trainer = t;
  save_checkpoint(dir, data);
}

// Restores weights, AdamW moments and RNG from `dir`; returns the step to continue from.
int64_t resume_training(const std::filesystem::path& dir, WanVae& vae, torch::optim::AdamW& opt) {
  const auto ck = Checkpoint::open(resolve_checkpoint_dir(dir));
  const auto report = load_state_dict(*vae, ck.model());
  DOJO_CHECK(report.ok(), "resume " + dir.string() + ": " + report.to_string("; "));
  if (!ck.has_trainer_state()) return 0;
  if (ck.has_trainer_tensors()) {
    // Checkpoints before the shared format named moments by parameter index ("adam.<i>.*").
    const auto tensors = named_adamw_state(ck.trainer_tensors().tensors(/*copy=*/true), *vae);
    load_adamw_state(opt, *vae, tensors);
    restore_rng_state(tensors);
  }
  LOG_INFO("resuming tokenizer training at step " + std::to_string(ck.step()));
  return ck.step();
}

}  // namespace

TokenizerTrainResult train_tokenizer(WanVae& vae, const std::function<torch::Tensor(int64_t)>& next_batch,
                                     const TokenizerTrainOptions& o) {
  check_training_precision("tokenizer train", o.precision);
  vae->to(o.device);  // before the optimiser sees the parameters
  vae->train();
  std::vector<torch::Tensor> params = vae->parameters();
  torch::optim::AdamW opt(params, torch::optim::AdamWOptions(o.lr).weight_decay(o.weight_decay));
  const bool checkpoints = !o.checkpoint_dir.empty();
  const int64_t start = checkpoints && o.resume && checkpoint_exists(o.checkpoint_dir)
                            ? resume_training(o.checkpoint_dir, vae, opt)
                            : 0;
  auto& group = data_parallel();
  group.check_same("the step to resume from", std::to_string(start));
  group.broadcast_from_main(*vae);
  const int64_t accumulate = std::max<int64_t>(1, o.accumulate);
  // The stream indices of this rank's micro-batches (their sizes are the loaders', tokenizer_batches).
  BatchShards split;
  split.accumulate = accumulate;
  split.world = group.world();
  split.rank = group.rank();
  auto image_batch = [&](int64_t step) {
    if (o.next_image_batch) return o.next_image_batch(step);
    const auto clips = next_batch(step);  // [B, 3, T, H, W]
    return clips.transpose(1, 2).reshape(
        {-1, clips.size(1), 1, clips.size(3), clips.size(4)});  // [B*T, 3, 1, H, W]
  };

  LoopOptions loop;
  loop.name = "tokenizer train";
  loop.steps = o.steps;
  loop.time_budget_s = o.time_budget_s;
  loop.save_every = checkpoints ? o.save_every : 0;
  loop.loss_curve = o.loss_curve;
  loop.columns = {"recon", "kl", "seconds", "images"};
  loop.unit = "frames";
  loop.progress = o.progress;
  TokenizerTrainResult result;
  bool first = true;
  const auto t0 = std::chrono::steady_clock::now();
  const auto run = run_training_loop(
      loop, start,
      [&](const LoopStep& s) {
        const bool images = std::max(static_cast<double>(s.index) / static_cast<double>(o.steps),
                                     s.budget_fraction) < o.image_fraction;
        const double lr = tokenizer_lr(o, s.index, s.budget_fraction);
        for (auto& group : opt.param_groups())
          static_cast<torch::optim::AdamWOptions&>(group.options()).lr(lr);
        opt.zero_grad();
        double recon = 0, kl = 0;
        int64_t frames = 0;
        for (int64_t j = 0; j < accumulate; ++j) {
          // Micro-batch j of this rank: its crop (and, split, its posterior draws) follow its
          // stream index; one process with one micro-batch keeps the plain run's draws.
          const int64_t index = split.stream_index(s.index, j);
          if (split.shards() > 1)
            torch::manual_seed(0x70CE11ULL * 0x9E3779B97F4A7C15ULL + static_cast<uint64_t>(index));
          const auto video = random_spatial_crop(images ? image_batch(s.index) : next_batch(s.index), o.crop,
                                                 static_cast<uint64_t>(index))
                                 .to(o.device);
          TokenizerLoss loss;
          {
            AutocastGuard autocast(o.device.type(), o.precision);
            loss = tokenizer_loss(vae, video, o);
          }
          (accumulate == 1 ? loss.total : loss.total / static_cast<double>(accumulate)).backward();
          recon += loss.mse.item<double>() / static_cast<double>(accumulate);
          kl += loss.kl.item<double>() / static_cast<double>(accumulate);
          frames += video.size(0) * video.size(2);
        }
        group.average_gradients(params);
        if (o.grad_clip > 0) torch::nn::utils::clip_grad_norm_(params, o.grad_clip);
        opt.step();
        const auto means = group.mean({recon, kl});
        recon = means[0];
        kl = means[1];
        if (first) result.first_loss = recon, first = false;
        result.last_loss = recon;
        char note[96];
        std::snprintf(note, sizeof note, "%s mse %.5f kl %.3f lr %.2g", images ? "images" : "clips", recon,
                      kl, lr);
        // After the last step, before its save: the latent normalisation from stats_batches batches
        // (each rank its share of them, the sums added over the ranks).
        if (s.last && o.stats_batches > 0) {
          std::vector<torch::Tensor> videos;
          for (int64_t i = 0; i < o.stats_batches * accumulate; ++i)
            videos.push_back(next_batch(o.steps + i).to(o.device));
          fit_latent_stats(vae, videos, group);
        }
        const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        return StepRecord{{recon, kl, seconds, images ? 1.0 : 0.0}, frames * group.world(), note};
      },
      [&](int64_t steps_done, bool) {
        if (checkpoints) save_training_checkpoint(o.checkpoint_dir, vae, opt, steps_done, o.trainer_extra);
      });
  result.steps_done = run.end_step;
  result.seconds = run.seconds;
  vae->eval();
  vae->to(torch::kCPU);  // where its callers' frames are
  return result;
}

TokenizerBatches tokenizer_batches(const std::vector<TokenizerDataset>& datasets,
                                   const data::ClipConfig& clip, int clip_batch, int image_batch, int workers,
                                   uint64_t seed, int64_t accumulate) {
  auto mixture = [&](int frames) {
    auto m = std::make_shared<data::ClipMixture>();
    data::ClipConfig c = clip;
    c.num_frames = frames;
    c.decoded_cache_mib = data::kTrainingDecodedCacheMib;
    for (const auto& d : datasets)
      m->add(std::make_shared<data::ClipDataset>(data::EpisodeStore::open(d.dir), c, d.split), d.weight);
    return m;
  };
  // One lazily started loader per stream; shared_ptr so the std::function copies share it.
  // One lazily started loader per stream; shared_ptr so the std::function copies share it. A
  // rank's loader hands out its runs of micro-batches of the whole stream (BatchShards).
  auto& group = data_parallel();
  auto stream = [workers](std::shared_ptr<data::ClipMixture> m, const BatchShards& shards,
                          uint64_t stream_seed) {
    auto loader = std::make_shared<std::unique_ptr<data::PrefetchLoader>>();
    data::LoaderOptions lo;
    lo.workers = workers;
    lo.seed = stream_seed;
    shards.share_stream(lo);
    return [=](int64_t step) {
      if (!*loader) *loader = std::make_unique<data::PrefetchLoader>(m, lo, step * lo.stream_run);
      return models::video_to_model((*loader)->next().video);  // [B, 3, T, H, W]
    };
  };
  TokenizerBatches b;
  b.clips = stream(mixture(clip.num_frames),
                   BatchShards::plan(clip_batch, accumulate, group, "tokenizer train"), seed);
  b.images = stream(mixture(1), BatchShards::plan(image_batch, accumulate, group, "tokenizer train (images)"),
                    seed ^ 0x9e3779b97f4a7c15ULL);
  return b;
}

void fit_latent_stats(WanVae& vae, const std::vector<torch::Tensor>& videos, DataParallel& group) {
  if (!group.active()) return fit_latent_stats(vae, videos);
  // Count, sum and sum of squares per latent channel, added over the ranks: the statistics of
  // every rank's batches together.
  torch::NoGradGuard no_grad;
  const int64_t z = vae->config().z_dim;
  auto sums = torch::zeros({2 * z + 1}, torch::kFloat64);
  for (const auto& v : videos) {
    const auto mu =
        vae->encode(v, false).mu.transpose(0, 1).reshape({z, -1}).to(torch::kCPU, torch::kFloat64);  // [z, n]
    sums.narrow(0, 0, z).add_(mu.sum(1));
    sums.narrow(0, z, z).add_(mu.pow(2).sum(1));
    sums[2 * z] += static_cast<double>(mu.size(1));
  }
  std::vector<double> local(sums.data_ptr<double>(), sums.data_ptr<double>() + sums.numel());
  auto total = group.mean(local);
  for (auto& t : total) t *= group.world();
  const double n = total[static_cast<size_t>(2 * z)];
  std::vector<double> mean(static_cast<size_t>(z)), stdv(static_cast<size_t>(z));
  for (int64_t c = 0; c < z; ++c) {
    mean[c] = total[c] / n;
    const double var = (total[z + c] - n * mean[c] * mean[c]) / std::max(1.0, n - 1);
    stdv[c] = std::max(std::sqrt(std::max(var, 0.0)), 1e-6);
  }
  vae->set_latent_stats(mean, stdv);
}

void fit_latent_stats(WanVae& vae, const std::vector<torch::Tensor>& videos) {
  torch::NoGradGuard no_grad;
  std::vector<torch::Tensor> mus;
  for (const auto& v : videos)
    mus.push_back(vae->encode(v, false).mu.transpose(0, 1).reshape({vae->config().z_dim, -1}));
  const auto all = torch::cat(mus, 1).to(torch::kCPU, torch::kFloat64);  // [z, N]
  const auto mean = all.mean(1), stdv = all.std(1).clamp_min(1e-6);
  std::vector<double> m(mean.data_ptr<double>(), mean.data_ptr<double>() + mean.numel());
  std::vector<double> s(stdv.data_ptr<double>(), stdv.data_ptr<double>() + stdv.numel());
  vae->set_latent_stats(m, s);
}

}  // namespace dojo::train
