#include "train/probe_train.h"

#include <ATen/CPUGeneratorImpl.h>
#include <torch/torch.h>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/state_dict.h"
#include "data/clip_loader.h"
#include "data/episode_store.h"
#include "train/train_loop.h"
#include "train/train_util.h"

namespace fs = std::filesystem;

namespace dojo::train {

torch::Tensor keypoint_probe_loss(const models::KeypointOutput& out, const torch::Tensor& target) {
  const auto present = target.select(-1, 2);                                    // [B, K]
  const auto l1 = (out.coords - target.narrow(-1, 0, 2)).abs().sum(-1);         // [B, K]
  const auto coord_loss = (l1 * present).sum() / present.sum().clamp_min(1.0);  // present points only
  return 10.0 * coord_loss + torch::binary_cross_entropy_with_logits(out.presence, present);
}

ProbeTrainResult run_probe_training(const ProbeTrainJob& job) {
  DOJO_CHECK(!job.datasets.empty(), "probe train: no dataset given");
  DOJO_CHECK(job.batch_size > 0 && job.steps >= 0, "probe train: batch and steps must be positive");
  fs::create_directories(job.out);
  const auto ckpt_dir = job.out / "checkpoint";
  const bool resuming = checkpoint_exists(ckpt_dir);
  const auto config = resuming ? models::KeypointProbeConfig::from_json(
                                     Checkpoint::open(resolve_checkpoint_dir(ckpt_dir)).config().at("config"))
                               : job.model;
  const auto frames = data::load_keypoint_frames(job.datasets, job.split, config.size);
  const auto targets = models::probe_targets(config, frames.embodiment, frames.keypoints);  // [N, K, 3]
  const int64_t n = frames.frames.size(0);
  LOG_INFO("probe train: ", n, " frames");

  torch::manual_seed(job.seed);
  models::KeypointProbe probe(config);
  AdamwLoop loop;
  loop.name = "probe train";
  loop.unit = "frames";
  loop.out = job.out;
  loop.prefix = "probe.";
  loop.steps = job.steps;
  loop.time_budget_s = job.time_budget_s;
  loop.save_every = job.save_every;
  loop.lr = job.lr;
  loop.seed = job.seed;
  loop.batch_size = job.batch_size;
  loop.accumulate = job.accumulate;
  loop.device = job.device;
  loop.precision = job.precision;
  const auto run = run_adamw_loop(
      *probe, loop, [&] { return models::keypoint_probe_checkpoint(*probe); },
      [&](const LoopStep&, int64_t batch, torch::Generator& gen) {
        // The batch, its augmentation and nothing else depend on (seed, step).
        const auto idx = torch::randint(n, {batch}, gen, torch::kLong);
        auto images = frames.frames.index_select(0, idx).permute({0, 3, 1, 2}).to(torch::kFloat32).div(255.0);
        const auto target = targets.index_select(0, idx);
        images = soften_like_generated(images, job.blur_probability, job.brightness, gen);
        return AdamwStep{
            keypoint_probe_loss(probe->forward(images.to(job.device)), target.to(job.device)), batch, {}};
      });
  probe->to(torch::kCPU);  // the caller's frames are on the CPU
  ProbeTrainResult r;
  r.steps = run.end_step;
  r.loss = run.loss;
  r.seconds = run.seconds;
  r.frames_per_second = run.items_per_second;
  probe->eval();
  return r;
}

}  // namespace dojo::train
