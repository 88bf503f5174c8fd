// Training the latent action model: one optimisation step (reconstruction MSE + beta * KL,
// AdamW, gradient-norm clipping) and the resumable loop over a dataset mixture that writes a
// loss curve and checkpoints.
#pragma once
#include <torch/torch.h>

#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "core/safetensors.h"
#include "models/lam.h"

namespace dojo::train {

struct LamTrainOptions {
  double lr = 2.5e-5;  // AdamW as released (torch default betas / eps)
  double weight_decay = 0.01;
  double beta = 1e-6;       // KL weight; see models::lam_loss for how the two terms scale
  double grad_clip = 0.3;   // max global gradient norm; <= 0 disables
  double brightness = 0.1;  // training augmentation: add U(-b, b) per sample, clamp to [0, 1]
  nlohmann::json to_json() const;
  static LamTrainOptions from_json(const nlohmann::json& j);
};

struct LamStepStats {
  double loss = 0, mse = 0, kl = 0;
  double grad_norm = 0;  // before clipping
  double psnr = 0;       // of the reconstruction, dB
};

class LamTrainer {
 public:
  LamTrainer(models::LatentActionModel model, LamTrainOptions options);
  // videos: [B, T >= 2, H, W, 3], float in [0, 1] or uint8. One AdamW step on them (no
  // augmentation here; see augment_brightness).
  LamStepStats step(const torch::Tensor& videos);
  int64_t steps_done() const { return steps_; }
  models::LatentActionModel& model() { return model_; }
  const LamTrainOptions& options() const { return options_; }

  // Optimizer moments as named tensors ("adamw.<param>.exp_avg" ...), and back.
  NamedTensors optimizer_state() const;
  void load_optimizer_state(const NamedTensors& tensors);
  // Checkpoint directory (core/checkpoint.h) with model config, weights, optimizer, step, RNG.
  void save(const std::filesystem::path& dir, const nlohmann::json& extra = nlohmann::json::object()) const;
  // Restores weights, optimizer state and step from a checkpoint written by save().
  void resume(const std::filesystem::path& dir);

 private:
  models::LatentActionModel model_;
  LamTrainOptions options_;
  std::unique_ptr<torch::optim::AdamW> optimizer_;
  int64_t steps_ = 0;
};

// uint8 [..] -> float in [0, 1]; float passes through.
torch::Tensor to_unit_float(const torch::Tensor& video);
// Adds one U(-amount, amount) offset per sample and clamps to [0, 1].
torch::Tensor augment_brightness(const torch::Tensor& videos, double amount, torch::Generator gen = {});

struct LamTrainJob {
  std::vector<std::pair<std::filesystem::path, double>> datasets;  // dataset dir, mixture weight
  std::filesystem::path out;  // checkpoint "out/checkpoint", loss curve "out/loss.csv"
  models::LamConfig model = models::LamConfig::small();
  LamTrainOptions options;
  int batch_size = 8;
  int64_t steps = 1000;  // total steps (a resumed job continues up to this)
  int64_t save_every = 200;
  int workers = 1;
  uint64_t seed = 0;
  double time_budget_s = 0;  // stop early (and checkpoint) after this long; 0: none
};
// Trains (resuming from out/checkpoint when present). Frame pairs are drawn with a uniformly
// random skip in {1, 2, 3, 4}. Returns the stats of the last step.
LamStepStats run_lam_training(const LamTrainJob& job);

}  // namespace dojo::train

namespace dojo::train {

// A checkpoint written by LamTrainer::save (or `dojo lam train`), in eval mode.
models::LatentActionModel load_lam(const std::filesystem::path& dir);

// Latent actions (z_mu) of every consecutive frame pair of one episode: frames [T, H, W, 3]
// uint8 (any size; centre-cropped and resized to the model's input) -> [T - 1, latent].
torch::Tensor lam_encode_episode(models::LatentActionModel& model, const torch::Tensor& frames,
                                 int64_t batch_pairs = 16);

struct LamLabelSummary {
  int64_t episodes = 0, pairs = 0;
  double seconds = 0;
};
// Writes out_dir/<episode id>.safetensors holding "z_mu" [T - 1, latent] and "z_logvar" for
// every episode of the dataset (out_dir defaults to DATASET/lam_latents), each file atomically;
// episodes whose file already exists are kept (re-running resumes).
LamLabelSummary label_lam_dataset(models::LatentActionModel& model, const std::filesystem::path& dataset,
                                  std::filesystem::path out_dir = {}, int64_t batch_pairs = 16);

struct ProbeResult {
  double r2_train = 0, r2_heldout = 0;  // mean over target dims of 1 - SSE / SST
  std::vector<double> r2_heldout_per_dim;
  int64_t n_train = 0, n_heldout = 0;
  int64_t target_dims = 0;
};

// What moved between frames t and t+1, for pairing with the latent action of that frame pair.
// `commanded` rows (actions, and human hand commands) are issued after frame t is observed and
// executed during step t (the LeRobot convention), so the pair's motion is cmd[t] - cmd[t-1] and
// the first pair has no target. Measured rows (poses observed with frame t) give pose[t+1] - pose[t].
struct ProbePairs {
  int64_t first_pair = 0;  // latent-action rows [first_pair, first_pair + deltas.size(0)) match
  torch::Tensor deltas;    // [n, K]
};
ProbePairs probe_deltas(const torch::Tensor& rows, bool commanded);
// Ridge regression (with intercept) from x [N, D] to y [N, K], fitted on the train rows.
ProbeResult ridge_probe(const torch::Tensor& x_train, const torch::Tensor& y_train,
                        const torch::Tensor& x_test, const torch::Tensor& y_test, double lambda = 1e-3);

}  // namespace dojo::train
