// Training the latent action model: one optimisation step (reconstruction MSE + beta * KL,
// AdamW, gradient-norm clipping) and the resumable loop over a dataset mixture that writes a
// loss curve and checkpoints.
#pragma once
#include <torch/torch.h>

#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

#include "core/autocast.h"
#include "core/safetensors.h"
#include "models/lam.h"
#include "train/fused_adamw.h"

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
  // The model and its AdamW moments live on `device`; with bf16 the forward pass runs under
  // autocast, weights, gradients and the loss stay float32 (fp16 is refused: no loss scaling).
  LamTrainer(models::LatentActionModel model, LamTrainOptions options, torch::Device device = torch::kCPU,
             Precision precision = Precision::kFloat32);
  // videos: [B, T >= 2, H, W, 3], float in [0, 1] or uint8, on any device (moved to the
  // trainer's). One AdamW step on them (no augmentation here; see augment_brightness).
  LamStepStats step(const torch::Tensor& videos);
  // One AdamW step on this process's micro-batches of a step: gradients accumulated over them and
  // averaged over the data-parallel ranks (data_parallel.h). With `seeds`, the model's own draws
  // (the posterior sample) for micro-batch j come from a generator seeded with seeds[j], so a split
  // of the batch draws what the whole batch would. Statistics are means over the global batch.
  LamStepStats step(const std::vector<torch::Tensor>& micro_batches, const std::vector<uint64_t>& seeds = {});
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
  torch::Device device_;
  Precision precision_;
  std::vector<torch::Tensor> params_;  // the trained ones (not the rotary frequencies)
  std::unique_ptr<torch::optim::AdamW> optimizer_;
  std::unique_ptr<FusedAdamW> fused_;  // views optimizer_'s state (fused_adamw.h)
  int64_t steps_ = 0;
};

// Adds one U(-amount, amount) offset per sample and clamps to [0, 1].
torch::Tensor augment_brightness(const torch::Tensor& videos, double amount, torch::Generator gen = {});

struct LamTrainJob {
  std::vector<std::pair<std::filesystem::path, double>> datasets;  // dataset dir, mixture weight
  std::filesystem::path out;  // checkpoint "out/checkpoint", loss curve "out/loss.csv"
  models::LamConfig model = models::LamConfig::small();
  LamTrainOptions options;
  int batch_size = 8;      // the global batch of a step, over every process
  int64_t accumulate = 1;  // micro-batches per step and process (data_parallel.h)
  int64_t steps = 1000;    // total steps (a resumed job continues up to this)
  int64_t save_every = 200;
  int workers = 1;
  uint64_t seed = 0;
  double time_budget_s = 0;            // stop early (and checkpoint) after this long; 0: none
  torch::Device device = torch::kCPU;  // where it trains (the loader's clips are moved there)
  Precision precision = Precision::kFloat32;
};
// Trains (resuming from out/checkpoint when present). Frame pairs are drawn with a uniformly
// random skip in {1, 2, 3, 4}. Returns the stats of the last step.
LamStepStats run_lam_training(const LamTrainJob& job);

}  // namespace dojo::train
