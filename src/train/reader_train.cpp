#include "train/reader_train.h"

#include <torch/torch.h>

#include <algorithm>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/safetensors.h"
#include "train/train_util.h"

namespace fs = std::filesystem;

namespace dojo::train {

SceneReadings SceneReadings::load(const fs::path& path) {
  const auto file = SafetensorsFile::open(path);
  SceneReadings d;
  d.frames = file.tensor("frames", true);
  d.values = file.tensor("values", true).to(torch::kFloat32);
  d.heldout = file.tensor("heldout", true).to(torch::kBool);
  const auto where = path.string() + ": ";
  DOJO_CHECK(d.frames.dim() == 4 && d.frames.size(3) == 3 && d.frames.scalar_type() == torch::kUInt8,
             where + "'frames' must be [N, H, W, 3] uint8");
  const int64_t N = d.frames.size(0);
  DOJO_CHECK(d.values.dim() == 2 && d.values.size(0) == N,
             where + "'values' must be [N, V], one row per frame");
  DOJO_CHECK(d.heldout.dim() == 1 && d.heldout.size(0) == N, where + "'heldout' must be [N]");
  DOJO_CHECK(torch::isfinite(d.values).all().item<bool>(), where + "'values' holds non-finite numbers");
  return d;
}

void SceneReadings::save(const fs::path& path) const {
  save_safetensors(path, {{"frames", frames}, {"values", values}, {"heldout", heldout.to(torch::kUInt8)}});
}

namespace {

// Values as sim::BinBelief lays them out: 0-1 the object's centre, 2 the grasp height, 4-5 the
// roll's (cos, sin), 6-7 the bin's centre.
constexpr int64_t kBeliefValues = 8;
constexpr double kBinInside = 0.075 - 0.01;  // as sim::BinBelief::object_in_bin

torch::Tensor in_bin(const torch::Tensor& v) {  // [N, 8] -> [N] bool
  return ((v.select(1, 0) - v.select(1, 6)).abs() < kBinInside) &
         ((v.select(1, 1) - v.select(1, 7)).abs() < kBinInside);
}

}  // namespace

ReaderErrors reader_errors(models::SceneReader& reader, const SceneReadings& data,
                           const torch::Tensor& which) {
  torch::NoGradGuard no_grad;
  reader->eval();
  DOJO_CHECK(reader->config().outputs == kBeliefValues && data.values.size(1) == kBeliefValues,
             "scene reader: errors are measured on the bin belief's 8 values");
  const auto index = which.to(torch::kBool).nonzero().flatten();
  ReaderErrors e;
  e.frames = index.numel();
  if (e.frames == 0) return e;
  std::vector<torch::Tensor> read;
  for (int64_t i = 0; i < e.frames; i += 256) {
    const auto part = index.narrow(0, i, std::min<int64_t>(256, e.frames - i));
    read.push_back(reader->denormalise(
        reader->forward(models::reader_input(reader, data.frames.index_select(0, part)))));
  }
  const auto got = torch::cat(read).to(torch::kFloat64),
             truth = data.values.index_select(0, index).to(torch::kFloat64);
  const auto distance_cm = [&](int64_t at) {
    return ((got.narrow(1, at, 2) - truth.narrow(1, at, 2)).pow(2).sum(1).sqrt().mean() * 100).item<double>();
  };
  e.object_cm = distance_cm(0);
  e.bin_cm = distance_cm(6);
  e.grasp_height_cm = ((got.select(1, 2) - truth.select(1, 2)).abs().mean() * 100).item<double>();
  e.in_bin_accuracy = (in_bin(got) == in_bin(truth)).to(torch::kFloat64).mean().item<double>();
  return e;
}

ReaderTrainResult run_reader_training(const ReaderTrainJob& job) {
  DOJO_CHECK(job.batch_size > 0 && job.steps >= 0, "reader train: batch must be positive and steps >= 0");
  const auto data = SceneReadings::load(job.data);
  fs::create_directories(job.out);
  const auto ckpt_dir = job.out / "checkpoint";
  const bool resuming = checkpoint_exists(ckpt_dir);
  auto config = resuming ? models::load_scene_reader(ckpt_dir)->config() : job.model;
  DOJO_CHECK(data.values.size(1) == config.outputs,
             job.data.string() + ": frames carry " + std::to_string(data.values.size(1)) +
                 " values; the reader reads " + std::to_string(config.outputs));
  const auto train = data.heldout.logical_not().nonzero().flatten();  // [N_train]
  DOJO_CHECK(train.numel() > 0, job.data.string() + ": no training frames (all are held out)");
  if (!resuming) {
    const auto v = data.values.index_select(0, train).to(torch::kFloat64);
    const auto mean = v.mean(0), scale = v.std(0).clamp_min(1e-3);
    config.value_mean.assign(mean.data_ptr<double>(), mean.data_ptr<double>() + mean.numel());
    config.value_scale.assign(scale.data_ptr<double>(), scale.data_ptr<double>() + scale.numel());
  }
  LOG_INFO("reader train: ", train.numel(), " training frames, ", data.heldout.sum().item<int64_t>(),
           " held out");

  torch::manual_seed(job.seed);
  models::SceneReader reader(config);
  const StepSnapshots snapshots(job.out, job.snapshots,
                                [&] { return models::scene_reader_checkpoint(*reader); });
  snapshots.before(resuming);
  AdamwLoop loop;
  loop.name = "reader train";
  loop.unit = "frames";
  loop.out = job.out;
  loop.prefix = "reader.";
  loop.steps = job.steps;
  loop.save_every = job.save_every;
  loop.lr = job.lr;
  loop.cosine = true;
  loop.seed = job.seed;
  loop.batch_size = job.batch_size;
  loop.accumulate = job.accumulate;
  const auto run = run_adamw_loop(
      *reader, loop, [&] { return models::scene_reader_checkpoint(*reader); },
      [&](const LoopStep&, int64_t batch, torch::Generator& gen) {
        const auto pick = train.index_select(0, torch::randint(train.numel(), {batch}, gen));
        auto images = models::reader_input(reader, data.frames.index_select(0, pick));  // [B, 3, S, S]
        images = soften_like_generated(images, job.blur_probability, job.brightness, gen);
        const auto target = reader->normalise(data.values.index_select(0, pick));  // [B, V]
        return AdamwStep{torch::mse_loss(reader->forward(images), target), images.size(0), {}};
      },
      [&](int64_t steps_done) { snapshots.after_step(steps_done); });
  snapshots.at_end(run.end_step, job.steps);  // the finished reader is a snapshot too
  ReaderTrainResult r;
  r.steps = run.end_step;
  r.loss = run.loss;
  r.seconds = run.seconds;
  r.heldout = reader_errors(reader, data, data.heldout);
  r.snapshots = list_step_snapshots(job.out);
  return r;
}

}  // namespace dojo::train
