// World-model training: the action-conditioned DiT learns rectified flow on tokenizer latents of
// 13-frame clips. Clips are encoded once by the frozen tokenizer (and, for human video, labelled
// once by the frozen LAM) into an in-memory latent cache that is also kept on disk, so training
// steps never touch video.
//
// Stages (DreamDojo §6):
//   pretrain   human video; actions are latent actions (or none / ground-truth motion: ablations)
//   posttrain  robot actions, starting from a pretrained checkpoint with the first layer of both
//              action MLPs re-drawn for the new action space
//   scratch    robot actions from a fresh network (the no-pretraining baseline)
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/autocast.h"
#include "diffusion/flow_matching.h"
#include "models/dit.h"

namespace dojo::train {

// What goes into the 384-d action rows of a clip.
enum class ActionMode {
  kDataset,      // the dataset's own rows (robot joints in their slot; human: the latent mask)
  kLatent,       // latent slot [352, 384) := mask * LAM latent action of each frame pair
  kNone,         // all zero (action-free pretraining)
  kGroundTruth,  // human hidden motion, chunk-relative, in the latent slot (upper-bound ablation)
};
ActionMode parse_action_mode(const std::string& text);  // dataset | latent | none | ground-truth
std::string to_string(ActionMode mode);

// Which clips to cache and how.
struct LatentCacheSpec {
  std::filesystem::path dataset;
  std::string split = "train";
  std::filesystem::path tokenizer;  // checkpoint directory
  std::filesystem::path lam;        // checkpoint directory (ActionMode::kLatent only)
  ActionMode mode = ActionMode::kDataset;
  std::vector<int> strides = {1, 2};
  int64_t hop = 2;               // window starts advance by this many frames
  int size = 0;                  // frame size fed to the tokenizer (0: the dataset's)
  int64_t max_clips = 0;         // 0: all windows
  bool relative_actions = true;  // false: absolute normalised actions (ablation)
  nlohmann::json to_json() const;
};

struct LatentClips {
  torch::Tensor latents;  // [N, 16, T_lat, h, w] normalised tokenizer latents
  torch::Tensor actions;  // [N, T - 1, 384] rows after the action mode
  nlohmann::json meta;    // the spec that made it
  int64_t size() const { return latents.defined() ? latents.size(0) : 0; }
};

// Loads `cache_file` when it was made from the same spec; otherwise encodes every window of the
// split and writes the file atomically.
LatentClips load_or_build_latent_clips(const LatentCacheSpec& spec, const std::filesystem::path& cache_file);

// Concatenates clip sets (their latent shapes must agree).
LatentClips concat_latent_clips(const std::vector<LatentClips>& sets);

struct WmTrainOptions {
  double lr = 1.6e-4;  // AdamW as released (betas 0.9/0.999)
  double weight_decay = 0.1;
  double grad_clip = 0.1;      // global norm, as released; <= 0 disables
  int64_t warmup_steps = 100;  // linear warm-up of the learning rate from 0
  double ema_sigma_rel = 0.1;  // power EMA, as released
  diffusion::FlowMatchingConfig flow;
  nlohmann::json to_json() const;
  static WmTrainOptions from_json(const nlohmann::json& j);
};

struct WmStepStats {
  double loss = 0, mse = 0, temporal = 0;
  double grad_norm = 0;  // before clipping
  double lr = 0;
};

class WmTrainer {
 public:
  // The network, its EMA copy and the AdamW moments live on `device`. With precision bf16 the
  // forward pass runs under autocast while weights, gradients, optimiser and loss stay float32;
  // fp16 (which would need loss scaling) is rejected.
  WmTrainer(models::ActionDit net, WmTrainOptions options, torch::Device device = torch::kCPU,
            Precision precision = Precision::kFloat32);
  // x0: [B, 16, T, h, w] clean latents, actions: [B, 4 (T - 1), 384], on any device (moved to
  // the trainer's). One optimiser step; the noise and time draws come from `generator` (a CPU
  // generator, so a seed gives the same draws on every device).
  WmStepStats step(const torch::Tensor& x0, const torch::Tensor& actions, torch::Generator generator);
  // Flow-matching loss of the EMA network on a fixed batch and fixed noise (no update).
  double eval_loss(const torch::Tensor& x0, const torch::Tensor& actions, uint64_t seed);

  models::ActionDit& net() { return net_; }
  models::ActionDit& ema() { return ema_; }
  int64_t steps_done() const { return steps_; }
  const WmTrainOptions& options() const { return options_; }
  const torch::Device& device() const { return device_; }
  Precision precision() const { return precision_; }

  // Checkpoint: model.safetensors holds the EMA weights as "net.*" (what inference loads, as
  // in the released converted checkpoints); trainer_state holds the raw weights, AdamW moments
  // and RNG. Always CPU float32 tensors, whatever the device and precision; resume() loads them
  // onto the trainer's device.
  void save(const std::filesystem::path& dir, const nlohmann::json& extra = nlohmann::json::object()) const;
  void resume(const std::filesystem::path& dir);

 private:
  double lr_at(int64_t step) const;

  models::ActionDit net_, ema_;
  WmTrainOptions options_;
  torch::Device device_;
  Precision precision_;
  std::vector<torch::Tensor> params_, ema_params_;
  std::unique_ptr<torch::optim::AdamW> optimizer_;
  double ema_gamma_;
  int64_t steps_ = 0;
};

enum class WmStage { kPretrain, kPosttrain, kScratch };
WmStage parse_wm_stage(const std::string& text);  // pretrain | posttrain | scratch
std::string to_string(WmStage stage);

struct WmTrainJob {
  WmStage stage = WmStage::kPretrain;
  std::vector<LatentCacheSpec> data;
  std::filesystem::path out;   // out/checkpoint, out/loss.csv, out/latents-<i>.safetensors
  std::filesystem::path init;  // posttrain: the pretrained checkpoint
  models::DitConfig model = models::DitConfig::small();
  WmTrainOptions options;
  int batch_size = 8;
  int64_t steps = 2000;      // total steps (a resumed job continues up to this)
  double time_budget_s = 0;  // wall-clock budget of the job, latent caching included; 0: none
  int64_t save_every = 100;
  uint64_t seed = 0;
  torch::Device device = torch::kCPU;         // where the network trains (latent caching stays on CPU)
  Precision precision = Precision::kFloat32;  // bf16: autocast forward, float32 master weights
};

struct WmTrainResult {
  int64_t steps = 0;                     // total steps done (including resumed ones)
  double first_loss = 0, last_loss = 0;  // smoothed training loss at the start / end of this run
  double heldout_loss_start = 0, heldout_loss_end = 0;  // EMA net on a fixed batch
  double seconds = 0, clips_per_second = 0;
  double gflops = 0;  // matmul work per second of training steps (3x forward FLOPs per clip)
  int64_t clips = 0;  // cached training clips
};

// Trains, resuming from out/checkpoint when it exists. Returns what the run measured.
WmTrainResult run_wm_training(const WmTrainJob& job);

// Saved world-model checkpoint -> EMA network in eval mode (float32, on `device`).
models::ActionDit load_world_model(const std::filesystem::path& dir, torch::Device device = torch::kCPU);

}  // namespace dojo::train
