#include "train/bc_train.h"

#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <set>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/safetensors.h"
#include "train/data_parallel.h"
#include "train/train_loop.h"
#include "train/train_util.h"

namespace fs = std::filesystem;

namespace dojo::train {

Demonstrations Demonstrations::load(const fs::path& path) {
  const auto file = SafetensorsFile::open(path);
  Demonstrations d;
  d.frames = file.tensor("frames", true);
  d.executed = file.tensor("executed", true).to(torch::kFloat32);
  d.labels = file.tensor("labels", true).to(torch::kFloat32);
  d.heldout = file.tensor("heldout", true).to(torch::kBool);
  const auto where = path.string() + ": ";
  DOJO_CHECK(d.frames.dim() == 5 && d.frames.size(4) == 3 && d.frames.scalar_type() == torch::kUInt8,
             where + "'frames' must be [E, T, H, W, 3] uint8");
  const int64_t E = d.frames.size(0), T = d.frames.size(1);
  for (const auto& [name, t] :
       {std::pair<const char*, const torch::Tensor&>{"executed", d.executed}, {"labels", d.labels}})
    DOJO_CHECK(t.dim() == 3 && t.size(0) == E && t.size(1) == T,
               where + "'" + name + "' must be [E, T, A], one row per frame");
  DOJO_CHECK(d.executed.size(2) == d.labels.size(2), where + "'executed' and 'labels' differ in width");
  DOJO_CHECK(d.heldout.dim() == 1 && d.heldout.size(0) == E, where + "'heldout' must be [E]");
  return d;
}

void Demonstrations::save(const fs::path& path) const {
  save_safetensors(path, {{"frames", frames},
                          {"executed", executed},
                          {"labels", labels},
                          {"heldout", heldout.to(torch::kUInt8)}});
}

namespace {

// Every (episode, frame) of episodes `which` from which a whole chunk of labels follows.
struct Samples {
  torch::Tensor episode, frame;  // [N] long each
};

Samples samples_of(const Demonstrations& data, const torch::Tensor& which, int64_t chunk) {
  const int64_t T = data.frames.size(1);
  std::vector<int64_t> episode, frame;
  const auto mask = which.to(torch::kBool);
  for (int64_t e = 0; e < data.frames.size(0); ++e) {
    if (!mask[e].item<bool>()) continue;
    for (int64_t t = 0; t + chunk <= T; ++t) {
      episode.push_back(e);
      frame.push_back(t);
    }
  }
  return {torch::tensor(episode, torch::kLong), torch::tensor(frame, torch::kLong)};
}

struct Batch {
  torch::Tensor frames, last, target;  // [B, H, W, 3] uint8, [B, A], [B, chunk, A] raw
};

Batch gather(const Demonstrations& data, const torch::Tensor& episode, const torch::Tensor& frame,
             int64_t chunk) {
  std::vector<torch::Tensor> frames, last, target;
  for (int64_t i = 0; i < episode.size(0); ++i) {
    const int64_t e = episode[i].item<int64_t>(), t = frame[i].item<int64_t>();
    frames.push_back(data.frames[e][t]);
    last.push_back(data.executed[e][t]);
    target.push_back(data.labels[e].narrow(0, t, chunk));
  }
  return {torch::stack(frames), torch::stack(last), torch::stack(target)};
}

// Per-dimension statistics of the training episodes: where commands sit and how far a chunk
// moves them (a floor keeps a dimension that never moves from dividing by zero).
void measure_statistics(const Demonstrations& data, const Samples& train, models::BcPolicyConfig& config) {
  const auto executed = data.executed.index({train.episode, train.frame});     // [N, A]
  const auto chunks = data.labels.unfold(1, config.chunk, 1).transpose(2, 3);  // [E, T-c+1, c, A]
  const auto offsets = chunks.index({train.episode, train.frame}) - executed.unsqueeze(1);  // [N, chunk, A]
  const auto to_vector = [](const torch::Tensor& t) {
    const auto d = t.to(torch::kFloat64).contiguous();
    return std::vector<double>(d.data_ptr<double>(), d.data_ptr<double>() + d.numel());
  };
  config.command_mean = to_vector(executed.mean(0));
  config.command_scale = to_vector(executed.std(0).clamp_min(1e-3));
  config.step_scale = to_vector(offsets.pow(2).mean(std::vector<int64_t>{0, 1}).sqrt().clamp_min(1e-3));
}

// Random translation by up to `shift` pixels: pad by replicating the border, crop at an offset.
torch::Tensor random_shift(const torch::Tensor& images, int64_t shift, torch::Generator& gen) {
  if (shift <= 0) return images;
  const int64_t B = images.size(0), S = images.size(2);
  const auto padded = torch::replication_pad2d(images, {shift, shift, shift, shift});
  const auto at = torch::randint(2 * shift + 1, {B, 2}, gen);
  std::vector<torch::Tensor> out;
  for (int64_t b = 0; b < B; ++b)
    out.push_back(padded[b].narrow(1, at[b][0].item<int64_t>(), S).narrow(2, at[b][1].item<int64_t>(), S));
  return torch::stack(out);
}

}  // namespace

double bc_loss(models::BcPolicy& policy, const Demonstrations& data, const torch::Tensor& which) {
  torch::NoGradGuard no_grad;
  policy->eval();
  const auto samples = samples_of(data, which, policy->config().chunk);
  const int64_t N = samples.episode.size(0);
  if (N == 0) return std::nan("");
  double sum = 0;
  for (int64_t i = 0; i < N; i += 256) {
    const int64_t n = std::min<int64_t>(256, N - i);
    const auto b =
        gather(data, samples.episode.narrow(0, i, n), samples.frame.narrow(0, i, n), policy->config().chunk);
    const auto predicted =
        policy->forward(models::bc_input(policy, b.frames), policy->normalise_command(b.last));
    sum +=
        (predicted - policy->commands_to_offsets(b.target, b.last)).pow(2).mean({1, 2}).sum().item<double>();
  }
  return sum / static_cast<double>(N);
}

BcTrainResult run_bc_training(const BcTrainJob& job) {
  DOJO_CHECK(job.batch_size > 0 && job.steps >= 0, "bc train: batch must be positive and steps >= 0");
  const auto data = Demonstrations::load(job.data);
  fs::create_directories(job.out);
  const auto ckpt_dir = job.out / "checkpoint";
  const bool resuming = checkpoint_exists(ckpt_dir);
  auto config = resuming ? models::load_bc_policy(ckpt_dir)->config() : job.model;
  DOJO_CHECK(data.executed.size(2) == config.action_dim,
             job.data.string() + ": commands have " + std::to_string(data.executed.size(2)) +
                 " values; the policy's action_dim is " + std::to_string(config.action_dim));
  const auto train = samples_of(data, data.heldout.logical_not(), config.chunk);
  DOJO_CHECK(train.episode.numel() > 0,
             job.data.string() + ": no training episode is long enough for a chunk");
  if (!resuming) measure_statistics(data, train, config);
  LOG_INFO("bc train: ", train.episode.numel(), " training samples from ",
           data.heldout.logical_not().sum().item<int64_t>(), " episodes");

  torch::manual_seed(job.seed);
  models::BcPolicy policy(config);
  const StepSnapshots snapshots(job.out, job.snapshots,
                                [&] { return models::bc_policy_checkpoint(*policy); });
  snapshots.before(resuming);
  AdamwLoop loop;
  loop.name = "bc train";
  loop.unit = "frames";
  loop.out = job.out;
  loop.prefix = "policy.";
  loop.steps = job.steps;
  loop.time_budget_s = job.time_budget_s;
  loop.save_every = job.save_every;
  loop.lr = job.lr;
  loop.cosine = true;
  loop.seed = job.seed;
  loop.batch_size = job.batch_size;
  loop.accumulate = job.accumulate;
  loop.device = job.device;
  loop.precision = job.precision;
  const auto run = run_adamw_loop(
      *policy, loop, [&] { return models::bc_policy_checkpoint(*policy); },
      [&](const LoopStep&, int64_t batch, torch::Generator& gen) {
        const auto pick = torch::randint(train.episode.numel(), {batch}, gen);
        const auto b = gather(data, train.episode.index_select(0, pick), train.frame.index_select(0, pick),
                              config.chunk);
        auto images = models::bc_input(policy, b.frames);  // [B, 3, S, S]
        images = random_shift(images, job.shift, gen);
        images = soften_like_generated(images, job.blur_probability, job.brightness, gen);
        const auto last = b.last.to(job.device);
        const auto predicted =
            policy->forward(images.to(job.device), policy->normalise_command(last));  // [B, chunk, A]
        return AdamwStep{
            torch::mse_loss(predicted, policy->commands_to_offsets(b.target.to(job.device), last)),
            images.size(0),
            {}};
      },
      [&](int64_t steps_done) { snapshots.after_step(steps_done); });
  policy->to(torch::kCPU);                    // scored below on the CPU's frames
  snapshots.at_end(run.end_step, job.steps);  // the finished policy is a snapshot too
  BcTrainResult r;
  r.steps = run.end_step;
  r.loss = run.loss;  // NaN when this call had nothing left to train
  r.seconds = run.seconds;
  r.heldout_loss = bc_loss(policy, data, data.heldout);
  r.snapshots = list_step_snapshots(job.out);
  return r;
}

}  // namespace dojo::train
