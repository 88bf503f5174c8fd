#include "train/value_train.h"

#include <torch/torch.h>

#include <algorithm>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/safetensors.h"
#include "train/train_util.h"

namespace fs = std::filesystem;

namespace dojo::train {

ValueData ValueData::load(const fs::path& path) {
  const auto file = SafetensorsFile::open(path);
  ValueData d;
  d.frames = file.tensor("frames", true);
  d.steps_to_boundary = file.tensor("steps_to_boundary", true).to(torch::kFloat32);
  d.heldout = file.tensor("heldout", true).to(torch::kBool);
  const auto where = path.string() + ": ";
  DOJO_CHECK(d.frames.dim() == 5 && d.frames.size(4) == 3 && d.frames.scalar_type() == torch::kUInt8,
             where + "'frames' must be [E, T, H, W, 3] uint8");
  const int64_t E = d.frames.size(0), T = d.frames.size(1);
  DOJO_CHECK(
      d.steps_to_boundary.dim() == 2 && d.steps_to_boundary.size(0) == E && d.steps_to_boundary.size(1) == T,
      where + "'steps_to_boundary' must be [E, T], one value per frame");
  DOJO_CHECK(torch::isfinite(d.steps_to_boundary).all().item<bool>() &&
                 (d.steps_to_boundary >= 0).all().item<bool>(),
             where + "'steps_to_boundary' must be finite and non-negative");
  DOJO_CHECK(d.heldout.dim() == 1 && d.heldout.size(0) == E, where + "'heldout' must be [E]");
  return d;
}

void ValueData::save(const fs::path& path) const {
  save_safetensors(
      path,
      {{"frames", frames}, {"steps_to_boundary", steps_to_boundary}, {"heldout", heldout.to(torch::kUInt8)}});
}

namespace {

torch::Tensor gather(const ValueData& data, const torch::Tensor& episode, const torch::Tensor& end,
                     int64_t window) {
  std::vector<torch::Tensor> out;
  for (int64_t i = 0; i < episode.size(0); ++i)
    out.push_back(
        data.frames[episode[i].item<int64_t>()].narrow(0, end[i].item<int64_t>() - window + 1, window));
  return torch::stack(out);  // [N, window, H, W, 3]
}

// Targets in [0, 1]: steps to the boundary over the horizon, capped.
torch::Tensor targets(const ValueData& data, const WindowEnds& w, int64_t horizon) {
  return (data.steps_to_boundary.index({w.episode, w.end}) / static_cast<double>(horizon)).clamp_max(1.0);
}

}  // namespace

ValueErrors value_errors(models::ValueModel& model, const ValueData& data, const torch::Tensor& which) {
  const auto w = window_ends(which, data.frames.size(1), model.window());
  ValueErrors e;
  e.windows = w.episode.numel();
  if (e.windows == 0) return e;
  std::vector<torch::Tensor> values;
  for (int64_t i = 0; i < e.windows; i += 256) {
    const int64_t n = std::min<int64_t>(256, e.windows - i);
    values.push_back(models::success_probability(
        model.network, gather(data, w.episode.narrow(0, i, n), w.end.narrow(0, i, n), model.window())));
  }
  const auto predicted = torch::cat(values).to(torch::kFloat64);
  const auto truth = targets(data, w, model.horizon).to(torch::kFloat64);
  e.mean_abs_steps = ((predicted - truth).abs().mean() * static_cast<double>(model.horizon)).item<double>();
  // Windows kGap steps apart in one episode whose targets fall (the same boundary ahead, closer).
  constexpr int64_t kGap = 8;
  if (e.windows > kGap) {
    const int64_t m = e.windows - kGap;
    const auto same = (w.episode.narrow(0, kGap, m) == w.episode.narrow(0, 0, m)) &
                      (w.end.narrow(0, kGap, m) - w.end.narrow(0, 0, m) == kGap);
    const auto pairs = same & (truth.narrow(0, kGap, m) < truth.narrow(0, 0, m));
    if (pairs.any().item<bool>()) {
      const auto right = predicted.narrow(0, kGap, m) < predicted.narrow(0, 0, m);
      e.order_accuracy = right.index({pairs}).to(torch::kFloat64).mean().item<double>();
    }
  }
  return e;
}

ValueTrainResult run_value_training(const ValueTrainJob& job) {
  DOJO_CHECK(job.batch_size > 0 && job.steps >= 0, "value train: batch must be positive and steps >= 0");
  const auto data = ValueData::load(job.data);
  fs::create_directories(job.out);
  const auto ckpt_dir = job.out / "checkpoint";
  torch::manual_seed(job.seed);
  auto model = checkpoint_exists(ckpt_dir) ? models::load_value_model(ckpt_dir)
                                           : models::make_value_model(job.horizon);
  model.network->train();
  const auto train = window_ends(data.heldout.logical_not(), data.frames.size(1), model.window());
  DOJO_CHECK(train.episode.numel() > 0, job.data.string() + ": no training window");
  LOG_INFO("value train: ", train.episode.numel(), " training windows, horizon ", model.horizon, " steps");
  AdamwLoop loop;
  loop.name = "value train";
  loop.unit = "windows";
  loop.out = job.out;
  loop.prefix = "value.";
  loop.steps = job.steps;
  loop.save_every = job.save_every;
  loop.lr = job.lr;
  loop.cosine = true;
  loop.seed = job.seed;
  loop.batch_size = job.batch_size;
  loop.accumulate = job.accumulate;
  const auto run = run_adamw_loop(
      *model.network, loop, [&] { return models::value_model_checkpoint(model); },
      [&](const LoopStep&, int64_t batch, torch::Generator& gen) {
        const auto pick = torch::randint(train.episode.numel(), {batch}, gen);
        const WindowEnds w{train.episode.index_select(0, pick), train.end.index_select(0, pick)};
        auto input = models::success_input(model.network, gather(data, w.episode, w.end, model.window()));
        input = soften_like_generated(input, job.blur_probability, job.brightness, gen);
        const auto value = torch::sigmoid(model.network->forward(input));  // [B]
        return AdamwStep{torch::mse_loss(value, targets(data, w, model.horizon)), batch, {}};
      });
  ValueTrainResult r;
  r.steps = run.end_step;
  r.loss = run.loss;
  r.seconds = run.seconds;
  r.heldout = value_errors(model, data, data.heldout);
  return r;
}

}  // namespace dojo::train
