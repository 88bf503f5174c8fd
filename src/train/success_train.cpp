#include "train/success_train.h"

#include <torch/torch.h>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/safetensors.h"
#include "train/train_loop.h"
#include "train/train_util.h"

namespace fs = std::filesystem;

namespace dojo::train {

SuccessData SuccessData::load(const fs::path& path) {
  const auto file = SafetensorsFile::open(path);
  SuccessData d;
  d.frames = file.tensor("frames", true);
  d.labels = file.tensor("labels", true).to(torch::kFloat32);
  d.heldout = file.tensor("heldout", true).to(torch::kBool);
  const auto where = path.string() + ": ";
  DOJO_CHECK(d.frames.dim() == 5 && d.frames.size(4) == 3 && d.frames.scalar_type() == torch::kUInt8,
             where + "'frames' must be [E, T, H, W, 3] uint8");
  DOJO_CHECK(
      d.labels.dim() == 2 && d.labels.size(0) == d.frames.size(0) && d.labels.size(1) == d.frames.size(1),
      where + "'labels' must be [E, T], one per frame");
  DOJO_CHECK(d.heldout.dim() == 1 && d.heldout.size(0) == d.frames.size(0), where + "'heldout' must be [E]");
  if (file.contains("simulator_frames")) {
    d.simulator_frames = file.tensor("simulator_frames", true);
    DOJO_CHECK(
        d.simulator_frames.sizes() == d.frames.sizes() && d.simulator_frames.scalar_type() == torch::kUInt8,
        where + "'simulator_frames' must be uint8 of the shape of 'frames'");
  }
  return d;
}

void SuccessData::save(const fs::path& path) const {
  NamedTensors tensors{{"frames", frames}, {"labels", labels}, {"heldout", heldout.to(torch::kUInt8)}};
  if (simulator_frames.defined()) tensors.emplace_back("simulator_frames", simulator_frames);
  save_safetensors(path, tensors);
}

namespace {

// The windows of episodes `which` and their labels.
struct Windows {
  torch::Tensor episode, end, label;  // [N] long, [N] long, [N] float
};

Windows windows_of(const SuccessData& data, const torch::Tensor& which, int64_t span) {
  const auto ends = window_ends(which, data.frames.size(1), span);
  const auto label = ends.episode.numel() ? data.labels.index({ends.episode, ends.end}) : torch::zeros({0});
  return {ends.episode, ends.end, label};
}

// uint8 windows [N, k, H, W, 3] ending at the given frames.
torch::Tensor gather_windows(const SuccessData& data, const torch::Tensor& episode, const torch::Tensor& end,
                             const models::SuccessDetectorConfig& config) {
  std::vector<torch::Tensor> out;
  for (int64_t i = 0; i < episode.size(0); ++i)
    out.push_back(
        models::window_ending_at(config, data.frames[episode[i].item<int64_t>()], end[i].item<int64_t>()));
  return torch::stack(out);
}

}  // namespace

SuccessAccuracy success_accuracy(models::SuccessDetector& detector, const SuccessData& data,
                                 const torch::Tensor& which) {
  const auto& config = detector->config();
  const auto w = windows_of(data, which, config.span());
  SuccessAccuracy a;
  a.windows = w.episode.size(0);
  if (a.windows == 0) return a;
  std::vector<torch::Tensor> probs;
  for (int64_t i = 0; i < a.windows; i += 256) {
    const int64_t n = std::min<int64_t>(256, a.windows - i);
    probs.push_back(models::success_probability(
        detector, gather_windows(data, w.episode.narrow(0, i, n), w.end.narrow(0, i, n), config)));
  }
  const auto predicted = torch::cat(probs) > 0.5;  // [N]
  const auto truth = w.label > 0.5;
  const auto right = (predicted == truth).to(torch::kFloat64);
  a.positives = truth.sum().item<int64_t>();
  a.accuracy = right.mean().item<double>();
  const auto rate = [&](const torch::Tensor& mask) {
    return mask.any().item<bool>() ? right.index({mask}).mean().item<double>() : 1.0;
  };
  a.balanced_accuracy = 0.5 * (rate(truth) + rate(truth.logical_not()));
  return a;
}

SuccessAccuracy episode_accuracy(models::SuccessDetector& detector, const SuccessData& data,
                                 const torch::Tensor& which, int64_t votes) {
  int64_t successes = 0, failures = 0, right_on_success = 0, right_on_failure = 0;
  const auto mask = which.to(torch::kBool);
  for (int64_t e = 0; e < data.frames.size(0); ++e) {
    if (!mask[e].item<bool>()) continue;
    const bool truth = data.labels[e][-1].item<float>() > 0.5f;  // the outcome at the episode's end
    const bool called = models::success_vote(detector, data.frames[e], votes) > 0.5;
    (truth ? successes : failures) += 1;
    (truth ? right_on_success : right_on_failure) += called == truth ? 1 : 0;
  }
  SuccessAccuracy a;
  a.windows = successes + failures;
  a.positives = successes;
  if (a.windows == 0) return a;
  a.accuracy = static_cast<double>(right_on_success + right_on_failure) / static_cast<double>(a.windows);
  // A class with no episodes counts as read right, as in success_accuracy.
  const auto rate = [](int64_t right, int64_t n) { return n ? static_cast<double>(right) / n : 1.0; };
  a.balanced_accuracy = 0.5 * (rate(right_on_success, successes) + rate(right_on_failure, failures));
  return a;
}

SuccessTrainResult run_success_training(const SuccessTrainJob& job) {
  DOJO_CHECK(job.batch_size > 1 && job.steps >= 0, "success train: batch must be > 1 and steps >= 0");
  const auto data = SuccessData::load(job.data);
  fs::create_directories(job.out);
  const auto ckpt_dir = job.out / "checkpoint";
  const bool resuming = checkpoint_exists(ckpt_dir);
  const auto config = resuming ? models::SuccessDetectorConfig::from_json(
                                     Checkpoint::open(resolve_checkpoint_dir(ckpt_dir)).config().at("config"))
                               : job.model;
  DOJO_CHECK(data.frames.size(1) >= config.span(), job.data.string() +
                                                       ": episodes are shorter than the detector's window (" +
                                                       std::to_string(config.span()) + " frames)");
  const auto train_windows = windows_of(data, data.heldout.logical_not(), config.span());
  const auto positive = torch::nonzero(train_windows.label > 0.5).flatten();
  const auto negative = torch::nonzero(train_windows.label <= 0.5).flatten();
  DOJO_CHECK(positive.numel() > 0 && negative.numel() > 0,
             job.data.string() + ": the training episodes need both success and failure frames");
  LOG_INFO("success train: ", train_windows.episode.size(0), " windows (", positive.numel(), " success)");

  torch::manual_seed(job.seed);
  models::SuccessDetector detector(config);
  AdamwLoop loop;
  loop.name = "success train";
  loop.unit = "windows";
  loop.out = job.out;
  loop.prefix = "detector.";
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
      *detector, loop, [&] { return models::success_detector_checkpoint(*detector); },
      [&](const LoopStep&, int64_t batch, torch::Generator& gen) {
        // Half the batch success windows, half failures; everything depends on (seed, step).
        const int64_t half = batch / 2;
        const auto pick =
            torch::cat({positive.index_select(0, torch::randint(positive.numel(), {half}, gen)),
                        negative.index_select(0, torch::randint(negative.numel(), {batch - half}, gen))});
        const auto episode = train_windows.episode.index_select(0, pick);
        const auto end = train_windows.end.index_select(0, pick);
        const auto target = train_windows.label.index_select(0, pick);  // [B]
        auto input =
            models::success_input(detector, gather_windows(data, episode, end, config));  // [B, 3k, S, S]
        const int64_t B = input.size(0);
        input = soften_like_generated(input, job.blur_probability, job.brightness, gen);
        // A mirrored scene is as successful as the original: flips double the scenes it sees.
        const auto flip = (torch::rand({B, 1, 1, 1}, gen) < 0.5).to(input.dtype());
        input = flip * input.flip({3}) + (1 - flip) * input;
        return AdamwStep{torch::binary_cross_entropy_with_logits(detector->forward(input.to(job.device)),
                                                                 target.to(job.device)),
                         B,
                         {}};
      });
  detector->to(torch::kCPU);  // scored below on the CPU's frames
  SuccessTrainResult r;
  r.steps = run.end_step;
  r.loss = run.loss;
  r.seconds = run.seconds;
  detector->eval();
  r.train = success_accuracy(detector, data, data.heldout.logical_not());
  r.heldout = success_accuracy(detector, data, data.heldout);
  r.heldout_episodes = episode_accuracy(detector, data, data.heldout, job.votes);
  if (data.simulator_frames.defined()) {
    SuccessData simulated{data.simulator_frames, data.labels, data.heldout, {}};
    r.simulator = {success_accuracy(detector, simulated, simulated.heldout),
                   episode_accuracy(detector, simulated, simulated.heldout, job.votes)};
  }
  return r;
}

}  // namespace dojo::train
