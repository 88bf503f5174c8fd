#include "train/tokenizer_trainer.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/progress.h"
#include "core/state_dict.h"
#include "data/clip_loader.h"
#include "data/episode_store.h"
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

TokenizerLoss tokenizer_loss(WanVae& vae, const torch::Tensor& video, double kl_weight, bool sample_posterior,
                             bool l1, double edge_weight) {
  auto enc = vae->encode(video, /*chunked=*/false);     // mu, log_var: [B, z, T', h, w]
  const auto log_var = enc.log_var.clamp(-30.0, 20.0);  // the release's clamp
  auto z = enc.mu;
  if (sample_posterior) z = z + torch::exp(0.5 * log_var) * torch::randn_like(z);
  const auto recon = vae->decode(z, /*chunked=*/false);  // [B, 3, T, H, W]
  TokenizerLoss loss;
  loss.mse = torch::mse_loss(recon, video);
  // L1 penalises small errors more than MSE does, which sharpens edges late in training.
  loss.recon = l1 ? torch::l1_loss(recon, video) : loss.mse;
  if (edge_weight > 0) loss.recon = loss.recon + edge_weight * edge_l1(recon, video);
  // KL(N(mu, sigma) || N(0, 1)), mean over latent elements.
  loss.kl = 0.5 * (enc.mu.pow(2) + log_var.exp() - 1.0 - log_var).mean();
  loss.total = loss.recon + kl_weight * loss.kl;
  return loss;
}

namespace {

// Adam moments as named tensors ("adam.<i>.exp_avg", ...), in parameter order.
NamedTensors adam_state(torch::optim::AdamW& opt, const std::vector<torch::Tensor>& params) {
  NamedTensors out;
  for (size_t i = 0; i < params.size(); ++i) {
    const auto key = c10::guts::to_string(params[i].unsafeGetTensorImpl());
    auto it = opt.state().find(key);
    if (it == opt.state().end()) continue;
    auto& s = static_cast<torch::optim::AdamWParamState&>(*it->second);
    const auto p = "adam." + std::to_string(i) + ".";
    out.emplace_back(p + "exp_avg", s.exp_avg());
    out.emplace_back(p + "exp_avg_sq", s.exp_avg_sq());
    out.emplace_back(p + "step", torch::tensor({s.step()}, torch::kInt64));
  }
  return out;
}

void restore_adam_state(torch::optim::AdamW& opt, const std::vector<torch::Tensor>& params,
                        const SafetensorsFile& file) {
  for (size_t i = 0; i < params.size(); ++i) {
    const auto p = "adam." + std::to_string(i) + ".";
    if (!file.contains(p + "exp_avg")) continue;
    auto s = std::make_unique<torch::optim::AdamWParamState>();
    s->exp_avg(file.tensor(p + "exp_avg", true));
    s->exp_avg_sq(file.tensor(p + "exp_avg_sq", true));
    s->step(file.tensor(p + "step").item<int64_t>());
    opt.state()[c10::guts::to_string(params[i].unsafeGetTensorImpl())] = std::move(s);
  }
}

void save_training_checkpoint(const std::filesystem::path& dir, WanVae& vae, torch::optim::AdamW& opt,
                              const std::vector<torch::Tensor>& params, int64_t step) {
  CheckpointData data;
  data.config = {{"model", "wan21_vae"}, {"config", vae->config().to_json()}};
  data.model = state_dict(*vae);
  TrainerState t;
  t.step = step;
  t.tensors = adam_state(opt, params);
  for (auto& r : capture_rng_state()) t.tensors.push_back(r);
  data.trainer = t;
  save_checkpoint(dir, data);
}

}  // namespace

TokenizerTrainResult train_tokenizer(WanVae& vae, const std::function<torch::Tensor(int64_t)>& next_batch,
                                     const TokenizerTrainOptions& o) {
  vae->train();
  std::vector<torch::Tensor> params = vae->parameters();
  torch::optim::AdamW opt(params, torch::optim::AdamWOptions(o.lr).weight_decay(o.weight_decay));
  int64_t start = 0;
  const bool checkpoints = !o.checkpoint_dir.empty();
  if (checkpoints && o.resume && std::filesystem::exists(o.checkpoint_dir)) {
    const auto ck = Checkpoint::open(o.checkpoint_dir);
    const auto report = load_state_dict(*vae, ck.model());
    DOJO_CHECK(report.ok(), "resume " + o.checkpoint_dir.string() + ": " + report.to_string("; "));
    if (ck.has_trainer_state()) {
      start = ck.step();
      if (ck.has_trainer_tensors()) {
        restore_adam_state(opt, params, ck.trainer_tensors());
        restore_rng_state(ck.trainer_tensors().tensors());
      }
      LOG_INFO("resuming tokenizer training at step " + std::to_string(start));
    }
  }
  TokenizerTrainResult result;
  const auto t0 = std::chrono::steady_clock::now();
  std::optional<Progress> progress;
  if (o.progress) progress.emplace("tokenizer train", o.steps - start, "step");
  bool first = true;
  TimeBudget budget(o.time_budget_s);
  if (progress) progress->set_time_budget(o.time_budget_s);
  std::optional<LossCurve> curve;
  if (!o.loss_curve.empty()) curve.emplace(o.loss_curve, "step,recon,kl,seconds,images", start);
  auto image_batch = [&](int64_t step) {
    if (o.next_image_batch) return o.next_image_batch(step);
    const auto clips = next_batch(step);  // [B, 3, T, H, W]
    return clips.transpose(1, 2).reshape(
        {-1, clips.size(1), 1, clips.size(3), clips.size(4)});  // [B*T, 3, 1, H, W]
  };
  for (int64_t step = start; step < o.steps; ++step) {
    const double budget_fraction =
        o.time_budget_s > 0 ? std::min(1.0, budget.elapsed() / o.time_budget_s) : 0.0;
    const bool images = std::max(static_cast<double>(step) / static_cast<double>(o.steps), budget_fraction) <
                        o.image_fraction;
    const auto video = random_spatial_crop(images ? image_batch(step) : next_batch(step), o.crop,
                                           static_cast<uint64_t>(step));
    const double lr = tokenizer_lr(o, step, budget_fraction);
    for (auto& group : opt.param_groups()) static_cast<torch::optim::AdamWOptions&>(group.options()).lr(lr);
    auto loss = tokenizer_loss(vae, video, o.kl_weight, o.sample_posterior, o.l1, o.edge_weight);
    opt.zero_grad();
    loss.total.backward();
    if (o.grad_clip > 0) torch::nn::utils::clip_grad_norm_(params, o.grad_clip);
    opt.step();
    const double recon = loss.mse.item<double>();
    if (first) result.first_loss = recon, first = false;
    result.last_loss = recon;
    if (progress) {
      char note[96];
      std::snprintf(note, sizeof note, "%s mse %.5f kl %.3f lr %.2g", images ? "images" : "clips", recon,
                    loss.kl.item<double>(), lr);
      progress->advance(1, note);
    }
    if (curve) {
      char row[128];
      std::snprintf(row, sizeof row, "%lld,%.6g,%.6g,%.2f,%d", static_cast<long long>(step + 1), recon,
                    loss.kl.item<double>(), budget.elapsed(), images ? 1 : 0);
      curve->add(row);
    }
    const bool out_of_time = budget.expired();
    const bool last = step + 1 == o.steps || out_of_time;
    if (last && o.stats_batches > 0) {
      std::vector<torch::Tensor> videos;
      for (int64_t i = 0; i < o.stats_batches; ++i) videos.push_back(next_batch(o.steps + i));
      fit_latent_stats(vae, videos);
    }
    if (checkpoints && (last || (o.save_every > 0 && (step + 1) % o.save_every == 0)))
      save_training_checkpoint(o.checkpoint_dir, vae, opt, params, step + 1);
    if (curve && (last || (o.save_every > 0 && (step + 1) % o.save_every == 0))) curve->write();
    result.steps_done = step + 1;
    if (out_of_time) {
      LOG_INFO("tokenizer train: time budget of ", o.time_budget_s, " s reached at step ", step + 1);
      break;
    }
  }
  if (progress) progress->finish();
  result.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  vae->eval();
  return result;
}

TokenizerBatches tokenizer_batches(const std::vector<TokenizerDataset>& datasets,
                                   const data::ClipConfig& clip, int clip_batch, int image_batch, int workers,
                                   uint64_t seed) {
  auto mixture = [&](int frames) {
    auto m = std::make_shared<data::ClipMixture>();
    data::ClipConfig c = clip;
    c.num_frames = frames;
    for (const auto& d : datasets)
      m->add(std::make_shared<data::ClipDataset>(data::EpisodeStore::open(d.dir), c, d.split), 1.0);
    return m;
  };
  // One lazily started loader per stream; shared_ptr so the std::function copies share it.
  auto stream = [workers](std::shared_ptr<data::ClipMixture> m, int batch, uint64_t stream_seed) {
    auto loader = std::make_shared<std::unique_ptr<data::PrefetchLoader>>();
    return [=](int64_t step) {
      if (!*loader)
        *loader = std::make_unique<data::PrefetchLoader>(
            m, data::LoaderOptions{batch, workers, 4, stream_seed}, step);
      return video_to_model((*loader)->next().video);  // [B, 3, T, H, W]
    };
  };
  TokenizerBatches b;
  b.clips = stream(mixture(clip.num_frames), clip_batch, seed);
  b.images = stream(mixture(1), image_batch, seed ^ 0x9e3779b97f4a7c15ULL);
  return b;
}

double psnr(const torch::Tensor& a, const torch::Tensor& b) {
  const double mse = ((a - b) * 0.5).pow(2).mean().item<double>();  // on [0, 1]
  return 10.0 * std::log10(1.0 / std::max(mse, 1e-12));
}

double ssim(const torch::Tensor& a, const torch::Tensor& b) {
  // Frames as a batch of images [N, C, H, W] in [0, 1]; Gaussian window 11, sigma 1.5.
  auto frames = [](const torch::Tensor& x) {
    return ((x.to(torch::kFloat32) + 1) * 0.5)
        .permute({0, 2, 1, 3, 4})
        .reshape({-1, x.size(1), x.size(3), x.size(4)});
  };
  const auto x = frames(a), y = frames(b);
  const int64_t c = x.size(1);
  const int64_t k = std::min<int64_t>({11, x.size(2), x.size(3)});
  auto g = torch::arange(k, torch::kFloat32) - (k - 1) / 2.0;
  g = torch::exp(-g.pow(2) / (2 * 1.5 * 1.5));
  g = g / g.sum();
  const auto w = (g.view({-1, 1}) * g.view({1, -1})).expand({c, 1, k, k}).contiguous();  // depthwise
  auto blur = [&](const torch::Tensor& t) {
    const std::vector<int64_t> one = {1, 1}, zero = {0, 0};
    return torch::conv2d(t, w, torch::Tensor(), one, zero, one, c);
  };
  const double c1 = 0.01 * 0.01, c2 = 0.03 * 0.03;
  const auto mx = blur(x), my = blur(y);
  const auto sxx = blur(x * x) - mx * mx, syy = blur(y * y) - my * my, sxy = blur(x * y) - mx * my;
  const auto s_map = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2));
  return s_map.mean().item<double>();
}

torch::Tensor reconstruct(WanVae& vae, const torch::Tensor& video) {
  torch::NoGradGuard no_grad;
  return vae->decode(vae->encode(video).mu).clamp(-1, 1);
}

void fit_latent_stats(WanVae& vae, const std::vector<torch::Tensor>& videos) {
  torch::NoGradGuard no_grad;
  std::vector<torch::Tensor> mus;
  for (const auto& v : videos)
    mus.push_back(vae->encode(v, false).mu.transpose(0, 1).reshape({vae->config().z_dim, -1}));
  const auto all = torch::cat(mus, 1).to(torch::kFloat64);  // [z, N]
  const auto mean = all.mean(1), stdv = all.std(1).clamp_min(1e-6);
  std::vector<double> m(mean.data_ptr<double>(), mean.data_ptr<double>() + mean.numel());
  std::vector<double> s(stdv.data_ptr<double>(), stdv.data_ptr<double>() + stdv.numel());
  vae->set_latent_stats(m, s);
}

torch::Tensor video_to_model(const torch::Tensor& u8) {
  return u8.permute({0, 4, 1, 2, 3}).to(torch::kFloat32) / 127.5 - 1.0;  // [B, 3, T, H, W]
}

torch::Tensor model_to_video(const torch::Tensor& x) {
  return ((x.clamp(-1, 1) + 1) * 127.5).round().to(torch::kUInt8).permute({0, 2, 3, 4, 1}).contiguous();
}

void save_tokenizer(const std::filesystem::path& dir, WanVae& vae) {
  CheckpointData data;
  data.config = {{"model", "wan21_vae"}, {"config", vae->config().to_json()}};
  data.model = state_dict(*vae);
  save_checkpoint(dir, data);
}

WanVae load_tokenizer(const std::filesystem::path& dir) {
  const auto ck = Checkpoint::open(dir);
  const auto& cfg = ck.config();
  DOJO_CHECK(cfg.contains("config"), ck.dir().string() + "/config.json: missing field 'config'");
  WanVae vae(models::WanVaeConfig::from_json(cfg.at("config")));
  const auto report = load_state_dict(*vae, ck.model());
  DOJO_CHECK(report.ok(), ck.dir().string() + ": " + report.to_string("; "));
  vae->eval();
  return vae;
}

}  // namespace dojo::train
