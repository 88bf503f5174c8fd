#include "train/lam_train.h"

#include <ATen/CPUGeneratorImpl.h>

#include <chrono>
#include <cmath>
#include <map>
#include <sstream>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "core/state_dict.h"
#include "data/clip_loader.h"
#include "data/episode_store.h"
#include "train/data_parallel.h"
#include "train/train_loop.h"
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
  const JsonFields f(j, "LAM train options");
  f.get("lr", o.lr);
  f.get("weight_decay", o.weight_decay);
  f.get("beta", o.beta);
  f.get("grad_clip", o.grad_clip);
  f.get("brightness", o.brightness);
  return o;
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

LamTrainer::LamTrainer(models::LatentActionModel model, LamTrainOptions options, torch::Device device,
                       Precision precision)
    : model_(std::move(model)), options_(options), device_(device), precision_(precision) {
  check_training_precision("lam train", precision_);
  model_->to(device_);  // before the optimiser sees the parameters
  for (auto& p : model_->parameters())
    if (p.requires_grad()) params_.push_back(p);  // rotary freqs are frozen
  // Every data-parallel rank starts from rank 0's weights.
  data_parallel().broadcast_from_main(*model_);
  optimizer_ = std::make_unique<torch::optim::AdamW>(
      params_, torch::optim::AdamWOptions(options_.lr).weight_decay(options_.weight_decay));
  // Clipping and AdamW in one pass over flat buffers: torch's per-tensor AdamW and clipping took
  // about 8 ms of the small LAM's ~100 ms step (docs/benchmarks.md). Every parameter takes part in
  // every forward pass, so every one has a gradient, as FusedAdamW assumes.
  fused_ = std::make_unique<FusedAdamW>(*optimizer_, params_);
}

LamStepStats LamTrainer::step(const torch::Tensor& videos_in) {
  return step(std::vector<torch::Tensor>{videos_in});
}

LamStepStats LamTrainer::step(const std::vector<torch::Tensor>& micro_batches,
                              const std::vector<uint64_t>& seeds) {
  model_->train();
  fused_->zero_grad();
  const auto count = static_cast<int64_t>(micro_batches.size());
  double loss = 0, mse = 0, kl = 0;
  for (int64_t j = 0; j < count; ++j) {
    if (!seeds.empty()) torch::manual_seed(seeds[j]);
    const auto videos = models::to_unit_float(micro_batches[j].to(device_));
    models::LamLoss l;
    {
      AutocastGuard autocast(device_.type(), precision_);
      l = models::lam_loss(model_->forward(videos), videos, options_.beta);
    }
    // One micro-batch alone is backpropagated unscaled: the step is bit for bit the plain one.
    (count == 1 ? l.total : l.total / static_cast<double>(count)).backward();
    loss += l.total.item<double>() / static_cast<double>(count);
    mse += l.mse.item<double>() / static_cast<double>(count);
    kl += l.kl.item<double>() / static_cast<double>(count);
  }
  auto& group = data_parallel();
  group.average_gradients(params_);
  LamStepStats s;
  s.grad_norm = fused_->step(options_.grad_clip, options_.lr, /*ema_beta=*/1.0);  // no EMA here
  ++steps_;
  const auto means = group.mean({loss, mse, kl});
  s.loss = means[0];
  s.mse = means[1];
  s.kl = means[2];
  s.psnr = -10.0 * std::log10(std::max(s.mse, 1e-12));
  return s;
}

NamedTensors LamTrainer::optimizer_state() const { return adamw_state(*optimizer_, *model_); }

void LamTrainer::load_optimizer_state(const NamedTensors& tensors) {
  load_adamw_state(*optimizer_, *model_, tensors);
  fused_->adopt_state();
}

void LamTrainer::save(const std::filesystem::path& dir, const nlohmann::json& extra) const {
  CheckpointData data = models::lam_checkpoint(*model_);
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

  models::LamConfig config = job.model;
  const bool resuming = checkpoint_exists(ckpt_dir);
  if (resuming)
    config = models::LamConfig::from_json(Checkpoint::open(resolve_checkpoint_dir(ckpt_dir)).config());
  torch::manual_seed(job.seed);
  LamTrainer trainer(models::LatentActionModel(config), job.options, job.device, job.precision);
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
  clip.decoded_cache_mib = data::kTrainingDecodedCacheMib;
  auto mixture = std::make_shared<data::ClipMixture>();
  for (const auto& [dir, weight] : job.datasets)
    mixture->add(std::make_shared<data::ClipDataset>(data::EpisodeStore::open(dir), clip, "train"), weight);
  auto& group = data_parallel();
  group.check_same("the step to resume from", std::to_string(trainer.steps_done()));
  const auto shards = BatchShards::plan(job.batch_size, job.accumulate, group, "lam train");
  data::LoaderOptions lo;
  lo.workers = job.workers;
  lo.seed = job.seed;
  shards.share_stream(lo);  // this rank's micro-batches of each step
  data::PrefetchLoader loader(mixture, lo, trainer.steps_done() * shards.accumulate);
  // One process, one micro-batch: the augmentation stream of a plain run. A split batch draws
  // each micro-batch's augmentation and posterior sample from its own (seed, stream index).
  const bool split = shards.shards() > 1;
  torch::Generator aug_gen = at::make_generator<at::CPUGeneratorImpl>(job.seed + 7919 * trainer.steps_done());

  LoopOptions loop;
  loop.name = "lam train";
  loop.steps = job.steps;
  loop.time_budget_s = job.time_budget_s;
  loop.save_every = job.save_every;
  loop.loss_curve = job.out / "loss.csv";
  loop.columns = {"loss", "mse", "kl", "psnr", "grad_norm", "clips_per_s"};
  LamStepStats last;
  const auto run = run_training_loop(
      loop, trainer.steps_done(),
      [&](const LoopStep& info) {
        std::vector<torch::Tensor> micro;
        std::vector<uint64_t> seeds;
        for (int64_t j = 0; j < shards.accumulate; ++j) {
          const auto batch = loader.next();
          const auto index = shards.stream_index(info.index, j);
          auto gen = split ? step_generator(job.seed + 7919, index) : aug_gen;
          micro.push_back(augment_brightness(models::to_unit_float(batch.video.slice(1, 0, 2)),
                                             job.options.brightness, gen));
          if (split)
            seeds.push_back(job.seed * 0x9E3779B97F4A7C15ULL + static_cast<uint64_t>(index) * 2654435761ULL +
                            17);
        }
        const auto t0 = std::chrono::steady_clock::now();
        last = trainer.step(micro, seeds);
        const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        const int64_t clips = job.batch_size;
        std::ostringstream note;
        note << "loss " << last.loss << " psnr " << last.psnr;
        return StepRecord{
            {last.loss, last.mse, last.kl, last.psnr, last.grad_norm, clips / secs}, clips, note.str()};
      },
      [&](int64_t, bool) { trainer.save(ckpt_dir); });
  if (run.items_per_second > 0)
    LOG_INFO("lam train: ", run.items_per_second, " clips/s (",
             run.items_per_second * 3 * models::lam_forward_flops(config) / 1e9, " GFLOP/s of matmul work)");
  return last;
}

}  // namespace dojo::train
