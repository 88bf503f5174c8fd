// Pieces every trainer shares: AdamW moments as named tensors (so checkpoints resume exactly),
// a loss-curve CSV that survives resumes, and a wall-clock budget.
#pragma once

#include <ATen/core/Generator.h>
#include <torch/nn/module.h>
#include <torch/optim/adamw.h>

#include <chrono>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include "core/autocast.h"
#include "core/checkpoint.h"
#include "core/safetensors.h"
#include "train/train_loop.h"

namespace dojo::train {

// The key torch::optim's per-parameter state map files a parameter under.
std::string optimizer_state_key(const torch::Tensor& param);

// AdamW moments of `module`'s parameters as "<prefix><param>.{exp_avg,exp_avg_sq,step}".
// Parameters the optimizer has not stepped yet are left out.
NamedTensors adamw_state(const torch::optim::AdamW& optimizer, const torch::nn::Module& module,
                         const std::string& prefix = "adamw.");
// Restores what adamw_state wrote; names absent from `tensors` are skipped (fresh moments).
void load_adamw_state(torch::optim::AdamW& optimizer, const torch::nn::Module& module,
                      const NamedTensors& tensors, const std::string& prefix = "adamw.");

// Moments saved by parameter index ("adam.<i>.{exp_avg,exp_avg_sq,step}", i counting
// module.parameters(): the tokenizer trainer's format before the shared one) renamed to the names
// adamw_state writes; every other tensor passes through unchanged.
NamedTensors named_adamw_state(NamedTensors tensors, const torch::nn::Module& module,
                               const std::string& prefix = "adamw.");

// Every (episode, last frame) of a whole window of `span` frames in the episodes that `which`
// ([E], nonzero = take) selects out of E episodes of `frames` frames each: episode-major, ends
// ascending. The windowed trainers (success detector, value model) draw their batches from these.
struct WindowEnds {
  torch::Tensor episode, end;  // [N] long each
};
WindowEnds window_ends(const torch::Tensor& which, int64_t frames, int64_t span);

// A CPU generator (so a seed gives the same draws on every device), and the one every trainer
// draws step k's batch and noise from: it depends on (seed, k) only, so a resumed run sees the
// same stream as an unbroken one. Draw i of a per-item stream (e.g. clip i's noise) uses the same.
torch::Generator cpu_generator(uint64_t seed);
torch::Generator step_generator(uint64_t seed, int64_t step);

// Clip indices into the concatenation of datasets of `sizes` clips. With one weight per dataset,
// a draw picks dataset d with probability weight[d] / sum(weights), then one of its clips
// uniformly: a small dataset keeps its share however many clips the others hold. Without weights
// every clip is alike (each dataset's share is its share of the clips). Draws depend on `gen` only.
class MixtureIndex {
 public:
  // Throws dojo::Error when weights and sizes differ in number, a weight is not positive or a
  // weighted dataset is empty.
  MixtureIndex(std::vector<int64_t> sizes, std::vector<double> weights = {});
  torch::Tensor draw(int64_t count, torch::Generator& gen) const;  // [count] int64
  std::vector<double> shares() const;                              // probability of drawing from each dataset
  bool weighted() const { return !weights_.empty(); }
  int64_t size() const { return offsets_.back() + sizes_.back(); }  // clips of all datasets
  // What checkpoints record: per dataset {"data": names[d], "clips", "weight" (null unweighted),
  // "share"}.
  nlohmann::json record(const std::vector<std::string>& names) const;

 private:
  std::vector<int64_t> sizes_, offsets_;
  std::vector<double> weights_, cumulative_;  // cumulative probabilities, last = 1
};

// Gaussian blur of each image of [B, C, S, S] with its own sigma [B] in pixels (0: untouched): the
// augmentation that keeps frame classifiers reading generated frames, which are softer than renders.
torch::Tensor gaussian_blur(const torch::Tensor& images, const torch::Tensor& sigma);
// The augmentation of frame readers that must read generated video (probe, success detector,
// policy): a brightness offset in [-brightness, brightness] per image, and with probability
// `blur_probability` a Gaussian blur of sigma 0.3-1.5 px; images [B, C, S, S] in [0, 1].
torch::Tensor soften_like_generated(const torch::Tensor& images, double blur_probability, double brightness,
                                    torch::Generator& gen);

// Snapshots kept along a run as models of their own (the policies and readers of policy
// evaluation): out/snapshots/step-NNNNNN, and those a run into `out` kept, in step order.
std::filesystem::path step_snapshot_dir(const std::filesystem::path& out, int64_t step);
std::vector<std::filesystem::path> list_step_snapshots(const std::filesystem::path& out);
// Keeps a run's snapshots at the steps in `at`: step 0 before a fresh run starts (before()), the
// others as their step ends (after_step(), run_adamw_loop's after_step), and the last step of a run
// that finished (at_end(); a run stopped early by its time budget leaves none: it would become a
// model of its own). `checkpoint` makes the model's inference checkpoint.
class StepSnapshots {
 public:
  StepSnapshots(std::filesystem::path out, std::vector<int64_t> at,
                std::function<CheckpointData()> checkpoint);
  void before(bool resuming) const;
  void after_step(int64_t steps_done) const;
  void at_end(int64_t end_step, int64_t steps) const;

 private:
  bool kept(int64_t step) const;
  void save(int64_t step) const;
  std::filesystem::path out_;
  std::vector<int64_t> at_;
  std::function<CheckpointData()> checkpoint_;
};

// Checkpoints of the plain AdamW loops (probe, fast decoder): `data` is the model's checkpoint
// (config and weights), to which the step and the AdamW moments are added as trainer state.
void save_with_adamw(const std::filesystem::path& dir, CheckpointData data,
                     const torch::optim::AdamW& optimizer, const torch::nn::Module& module, int64_t step);
// Loads what save_with_adamw wrote: weights under `prefix` into `module` (strict) and the moments
// into `optimizer`. Returns the step.
int64_t resume_with_adamw(const std::filesystem::path& dir, torch::nn::Module& module,
                          const std::string& prefix, torch::optim::AdamW& optimizer);

// The plain AdamW loop of the small models (keypoint probe, success detector, policy, fast
// decoder) on top of run_training_loop: the optimizer, resuming from out/checkpoint (weights under
// `prefix` and the moments, save_with_adamw), a linear warm-up then a constant rate or a cosine
// decay to a tenth, the loss curve out/loss.csv ("loss", "lr", then `extra_columns`), saves, and
// the mean loss of the last 20 steps. The model is built by the caller (from the checkpoint's
// config when resuming) and left in train mode. Under data parallelism (data_parallel.h) the
// parameters start from rank 0's, gradients are averaged over the ranks and rank 0 alone saves and
// runs after_step; the step function gets the micro-batch size to draw and that micro-batch's
// generator, and `loss` is the mean over the whole global batch.
struct AdamwLoop {
  std::string name;  // progress label and log prefix, e.g. "probe train"
  std::string unit = "items";
  std::filesystem::path out;  // out/checkpoint, out/loss.csv
  std::string prefix;         // the model's weight prefix in its checkpoint, e.g. "probe."
  int64_t steps = 0;          // total; a resumed run continues up to this
  int64_t save_every = 0;
  double time_budget_s = 0;
  double lr = 1e-3, weight_decay = 1e-4;
  int64_t warmup_steps = 50;
  bool cosine = false;
  uint64_t seed = 0;  // every step draws from step_generator(seed, step): resumes continue the stream
  std::vector<std::string> extra_columns;
  // The global batch of a step, split into world x accumulate micro-batches (data_parallel.h):
  // the step function is asked for one micro-batch at a time, drawn from its own generator.
  int64_t batch_size = 0;
  int64_t accumulate = 1;
  // Where the model trains: it is moved there before the optimiser sees it (and stays there); the
  // step function runs under autocast at `precision` (the backward pass outside it) and moves its
  // batch to `device`. Draws stay on the CPU; checkpoints are float32 and load on any device.
  torch::Device device = torch::kCPU;
  Precision precision = Precision::kFloat32;
};
struct AdamwStep {
  torch::Tensor loss;         // the scalar to minimise
  int64_t items = 0;          // samples in the batch, for throughput
  std::vector<double> extra;  // one per extra column (NaN: empty cell)
};
struct AdamwRun {
  int64_t start_step = 0, end_step = 0;
  double loss = 0;  // mean of the last 20 steps of this run; NaN when it ran none
  double seconds = 0, items_per_second = 0;
};
AdamwRun run_adamw_loop(
    torch::nn::Module& model, const AdamwLoop& loop, const std::function<CheckpointData()>& checkpoint,
    const std::function<AdamwStep(const LoopStep&, int64_t batch, torch::Generator&)>& step,
    const std::function<void(int64_t steps_done)>& after_step = {});

// A CSV loss curve: header row plus one row per step, rewritten atomically. Opening an existing
// file keeps rows up to `resume_step` (rows written after the last checkpoint are dropped, so a
// resumed run does not leave duplicate steps).
class LossCurve {
 public:
  LossCurve(std::filesystem::path path, const std::string& header, int64_t resume_step);
  void add(const std::string& row) { rows_.push_back(row); }
  void write() const;
  const std::filesystem::path& path() const { return path_; }

 private:
  std::filesystem::path path_;
  std::vector<std::string> rows_;
};

// Wall-clock budget: expired() once `seconds` have passed since construction (never when
// seconds <= 0).
class TimeBudget {
 public:
  explicit TimeBudget(double seconds) : seconds_(seconds), start_(std::chrono::steady_clock::now()) {}
  double elapsed() const {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  }
  bool expired() const { return seconds_ > 0 && elapsed() >= seconds_; }
  double seconds() const { return seconds_; }

 private:
  double seconds_;
  std::chrono::steady_clock::time_point start_;
};

}  // namespace dojo::train
