#include "train/lam_train.h"

#include <ATen/CPUGeneratorImpl.h>

#include <chrono>
#include <cmath>
#include <limits>
#include <map>
#include <sstream>

#include "core/atomic_file.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/progress.h"
#include "core/state_dict.h"
#include "data/clip_loader.h"
#include "data/episode_store.h"
#include "io/video.h"
#include "train/train_util.h"

namespace dojo::train {

nlohmann::json LamTrainOptions::to_json() const {
  return {{"lr", lr},
          {"weight_decay", weight_decay},
          {"beta", beta},
          {"grad_clip", grad_clip},
          {"brightness", brightness}};
}

LamTrainOptions LamTrainOptions::from_json(const nlohmann::json& j) {
  LamTrainOptions o;
  auto get = [&](const char* key, double& v) {
    if (!j.contains(key)) return;
    DOJO_CHECK(j[key].is_number(), std::string("LAM train options: field '") + key + "' must be a number");
    v = j[key].get<double>();
  };
  get("lr", o.lr);
  get("weight_decay", o.weight_decay);
  get("beta", o.beta);
  get("grad_clip", o.grad_clip);
  get("brightness", o.brightness);
  return o;
}

torch::Tensor to_unit_float(const torch::Tensor& video) {
  if (video.scalar_type() == torch::kByte) return video.to(torch::kFloat).div_(255.0);
  return video.to(torch::kFloat);
}

torch::Tensor augment_brightness(const torch::Tensor& videos, double amount, torch::Generator gen) {
  if (amount <= 0) return videos;
  std::vector<int64_t> shape(videos.dim(), 1);
  shape[0] = videos.size(0);
  auto offset =
      gen.defined() ? torch::rand(shape, gen, videos.options()) : torch::rand(shape, videos.options());
  offset.mul_(2 * amount).sub_(amount);  // [B, 1, 1, 1, 1]
  return (videos + offset).clamp_(0.0, 1.0);
}

LamTrainer::LamTrainer(models::LatentActionModel model, LamTrainOptions options)
    : model_(std::move(model)), options_(options) {
  std::vector<torch::Tensor> params;
  for (auto& p : model_->parameters())
    if (p.requires_grad()) params.push_back(p);  // rotary freqs are frozen
  optimizer_ = std::make_unique<torch::optim::AdamW>(
      params, torch::optim::AdamWOptions(options_.lr).weight_decay(options_.weight_decay));
}

LamStepStats LamTrainer::step(const torch::Tensor& videos_in) {
  model_->train();
  const auto videos = to_unit_float(videos_in);
  optimizer_->zero_grad();
  const auto out = model_->forward(videos);
  const auto loss = models::lam_loss(out, videos, options_.beta);
  loss.total.backward();
  LamStepStats s;
  double clip = options_.grad_clip > 0 ? options_.grad_clip : std::numeric_limits<double>::infinity();
  s.grad_norm = torch::nn::utils::clip_grad_norm_(optimizer_->param_groups()[0].params(), clip);
  optimizer_->step();
  ++steps_;
  s.loss = loss.total.item<double>();
  s.mse = loss.mse.item<double>();
  s.kl = loss.kl.item<double>();
  s.psnr = -10.0 * std::log10(std::max(s.mse, 1e-12));
  return s;
}

NamedTensors LamTrainer::optimizer_state() const { return adamw_state(*optimizer_, *model_); }

void LamTrainer::load_optimizer_state(const NamedTensors& tensors) {
  load_adamw_state(*optimizer_, *model_, tensors);
}

void LamTrainer::save(const std::filesystem::path& dir, const nlohmann::json& extra) const {
  CheckpointData data;
  data.config = model_->config.to_json();
  for (const auto& [name, t] : state_dict(*model_)) data.model.emplace_back("lam." + name, t);
  TrainerState ts;
  ts.step = steps_;
  ts.extra = extra;
  ts.extra["options"] = options_.to_json();
  ts.tensors = optimizer_state();
  for (auto& t : capture_rng_state()) ts.tensors.push_back(t);
  data.trainer = ts;
  save_checkpoint(dir, data);
}

void LamTrainer::resume(const std::filesystem::path& dir) {
  auto ckpt = Checkpoint::open(dir);
  LoadOptions opts;
  opts.prefix = "lam.";
  load_state_dict(*model_, ckpt.model(), opts);
  steps_ = ckpt.has_trainer_state() ? ckpt.step() : 0;
  if (ckpt.has_trainer_tensors()) {
    const auto tensors = ckpt.trainer_tensors().tensors(/*copy=*/true);
    load_optimizer_state(tensors);
    restore_rng_state(tensors);
  }
}

LamStepStats run_lam_training(const LamTrainJob& job) {
  DOJO_CHECK(!job.datasets.empty(), "lam train: no dataset given");
  std::filesystem::create_directories(job.out);
  const auto ckpt_dir = job.out / "checkpoint";
  const auto curve = job.out / "loss.csv";

  models::LamConfig config = job.model;
  const bool resuming =
      std::filesystem::exists(ckpt_dir) || std::filesystem::exists(ckpt_dir.string() + ".dojo-old");
  if (resuming) config = models::LamConfig::from_json(Checkpoint::open(ckpt_dir).config());
  torch::manual_seed(job.seed);
  LamTrainer trainer(models::LatentActionModel(config), job.options);
  if (resuming) {
    trainer.resume(ckpt_dir);
    LOG_INFO("lam train: resumed from ", ckpt_dir.string(), " at step ", trainer.steps_done());
  }

  // Frame pairs at a uniformly random skip in {1, 2, 3, 4}, at the model's input size. The clip
  // loader's action pipeline needs num_frames - 1 to be a whole number of action chunks, so clips
  // of 5 frames (one chunk of 4) are read and their first two frames used.
  data::ClipConfig clip;
  clip.num_frames = 5;
  clip.strides = {1, 2, 3, 4};
  clip.action_chunk = 4;
  clip.height = static_cast<int>(config.height);
  clip.width = static_cast<int>(config.width);
  auto mixture = std::make_shared<data::ClipMixture>();
  for (const auto& [dir, weight] : job.datasets)
    mixture->add(std::make_shared<data::ClipDataset>(data::EpisodeStore::open(dir), clip, "train"), weight);
  data::LoaderOptions lo;
  lo.batch_size = job.batch_size;
  lo.workers = job.workers;
  lo.seed = job.seed;
  data::PrefetchLoader loader(mixture, lo, trainer.steps_done());

  // Loss curve: CSV with a header, appended across resumes (rows past the resume step dropped).
  LossCurve loss_curve(curve, "step,loss,mse,kl,psnr,grad_norm,clips_per_s", trainer.steps_done());

  torch::Generator aug_gen = at::make_generator<at::CPUGeneratorImpl>(job.seed + 7919 * trainer.steps_done());
  Progress progress("lam train", job.steps - trainer.steps_done(), "step");
  LamStepStats last;
  int64_t seen_steps = 0, timed_steps = 0;
  double timed_clips = 0, timed_seconds = 0;
  TimeBudget budget(job.time_budget_s);
  progress.set_time_budget(job.time_budget_s);
  while (trainer.steps_done() < job.steps) {
    auto batch = loader.next();
    const auto t0 = std::chrono::steady_clock::now();
    auto videos =
        augment_brightness(to_unit_float(batch.video.slice(1, 0, 2)), job.options.brightness, aug_gen);
    last = trainer.step(videos);
    const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::ostringstream row;
    row << trainer.steps_done() << ',' << last.loss << ',' << last.mse << ',' << last.kl << ',' << last.psnr
        << ',' << last.grad_norm << ',' << batch.video.size(0) / secs;
    loss_curve.add(row.str());
    if (++seen_steps > 2) {  // the first steps warm up allocators and threads
      ++timed_steps;
      timed_clips += static_cast<double>(batch.video.size(0));
      timed_seconds += secs;
    }
    std::ostringstream note;
    note << "loss " << last.loss << " psnr " << last.psnr;
    progress.advance(1, note.str());
    const bool out_of_time = budget.expired();
    if (trainer.steps_done() % job.save_every == 0 || trainer.steps_done() == job.steps || out_of_time) {
      trainer.save(ckpt_dir);
      loss_curve.write();
    }
    if (out_of_time) {
      LOG_INFO("lam train: time budget of ", job.time_budget_s, " s reached at step ", trainer.steps_done());
      break;
    }
  }
  progress.finish();
  loss_curve.write();
  if (timed_steps > 0) {
    const double clips_per_s = timed_clips / timed_seconds;
    LOG_INFO("lam train: ", clips_per_s, " clips/s over ", timed_steps, " steps (",
             clips_per_s * 3 * models::lam_forward_flops(config) / 1e9, " GFLOP/s of matmul work)");
  }
  return last;
}

}  // namespace dojo::train

namespace dojo::train {

models::LatentActionModel load_lam(const std::filesystem::path& dir) {
  auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  models::LatentActionModel model(models::LamConfig::from_json(ckpt.config()));
  LoadOptions opts;
  opts.prefix = "lam.";
  load_state_dict(*model, ckpt.model(), opts);
  model->eval();
  return model;
}

torch::Tensor lam_encode_episode(models::LatentActionModel& model, const torch::Tensor& frames,
                                 int64_t batch_pairs) {
  torch::NoGradGuard no_grad;
  model->eval();
  const auto& c = model->config;
  auto f = frames;
  if (f.size(1) != c.height || f.size(2) != c.width) f = io::resize_center_crop(f, c.height, c.width);
  const auto video = to_unit_float(f);  // [T, h, w, 3]
  const int64_t T = video.size(0);
  std::vector<torch::Tensor> out;
  for (int64_t s = 0; s < T - 1; s += batch_pairs) {
    const int64_t e = std::min(T - 1, s + batch_pairs);
    auto pairs = torch::stack({video.slice(0, s, e), video.slice(0, s + 1, e + 1)}, 1);  // [n, 2, h, w, 3]
    out.push_back(model->encode(pairs).z_mu);
  }
  return out.empty() ? torch::zeros({0, c.latent_dim}) : torch::cat(out, 0);
}

LamLabelSummary label_lam_dataset(models::LatentActionModel& model, const std::filesystem::path& dataset,
                                  std::filesystem::path out_dir, int64_t batch_pairs) {
  const auto t0 = std::chrono::steady_clock::now();
  auto store = data::EpisodeStore::open(dataset);
  if (out_dir.empty()) out_dir = dataset / "lam_latents";
  std::filesystem::create_directories(out_dir);
  LamLabelSummary s;
  Progress progress("lam label", static_cast<int64_t>(store.size()), "episode");
  for (size_t i = 0; i < store.size(); ++i) {
    const auto path = out_dir / (store.info().episodes[i].id + ".safetensors");
    if (!std::filesystem::exists(path)) {
      auto ep = store.load(i);
      torch::NoGradGuard no_grad;
      model->eval();
      const auto mu = lam_encode_episode(model, ep.frames, batch_pairs);
      Metadata meta;
      meta["config"] = model->config.to_json().dump();
      save_safetensors(path, {{"z_mu", mu}}, meta);
      s.pairs += mu.size(0);
    }
    ++s.episodes;
    progress.advance();
  }
  progress.finish();
  s.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return s;
}

ProbeResult ridge_probe(const torch::Tensor& x_train, const torch::Tensor& y_train,
                        const torch::Tensor& x_test, const torch::Tensor& y_test, double lambda) {
  DOJO_CHECK(x_train.size(0) > 1 && x_test.size(0) > 1, "lam probe: too few samples to fit and evaluate");
  auto xt = x_train.to(torch::kDouble), yt = y_train.to(torch::kDouble);
  auto xm = xt.mean(0), xs = xt.std(0).clamp_min(1e-8), ym = yt.mean(0);
  auto norm = [&](const torch::Tensor& x) { return (x.to(torch::kDouble) - xm) / xs; };
  auto a = norm(xt);
  const int64_t D = a.size(1);
  auto w = torch::linalg_solve(a.t().mm(a) + lambda * a.size(0) * torch::eye(D, torch::kDouble),
                               a.t().mm(yt - ym));
  auto r2 = [&](const torch::Tensor& x, const torch::Tensor& y) {
    auto yd = y.to(torch::kDouble);
    auto pred = norm(x).mm(w) + ym;
    auto sse = (yd - pred).pow(2).sum(0);
    auto sst = (yd - yd.mean(0)).pow(2).sum(0).clamp_min(1e-12);
    return (1 - sse / sst).mean().item<double>();
  };
  ProbeResult r;
  {
    auto yd = y_test.to(torch::kDouble);
    auto sse = (yd - (norm(x_test).mm(w) + ym)).pow(2).sum(0);
    auto per_dim = (1 - sse / (yd - yd.mean(0)).pow(2).sum(0).clamp_min(1e-12)).contiguous();
    r.r2_heldout_per_dim.assign(per_dim.data_ptr<double>(), per_dim.data_ptr<double>() + per_dim.numel());
  }
  r.r2_train = r2(x_train, y_train);
  r.r2_heldout = r2(x_test, y_test);
  r.n_train = x_train.size(0);
  r.n_heldout = x_test.size(0);
  r.target_dims = y_train.size(1);
  return r;
}

ProbePairs probe_deltas(const torch::Tensor& rows, bool commanded) {
  DOJO_CHECK(rows.dim() == 2 && rows.size(0) >= 3, "lam probe: need at least 3 rows of targets per episode");
  const int64_t T = rows.size(0);
  ProbePairs p;
  if (commanded) {
    p.first_pair = 1;
    p.deltas = rows.slice(0, 1, T - 1) - rows.slice(0, 0, T - 2);  // pairs 1..T-2: cmd[t] - cmd[t-1]
  } else {
    p.deltas = rows.slice(0, 1) - rows.slice(0, 0, -1);  // pairs 0..T-2: pose[t+1] - pose[t]
  }
  return p;
}

}  // namespace dojo::train
