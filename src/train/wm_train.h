// World-model training: the action-conditioned DiT learns rectified flow on tokenizer latents of
// 13-frame clips, read from the latent cache (train/latent_cache.h), so training steps never
// touch video.
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
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/autocast.h"
#include "diffusion/flow_matching.h"
#include "models/dit.h"
#include "train/fused_adamw.h"
#include "train/latent_cache.h"
#include "train/overlapped_average.h"

namespace dojo::train {

struct WmTrainOptions {
  double lr = 1.6e-4;  // AdamW as released (betas 0.9/0.999)
  double weight_decay = 0.1;
  double grad_clip = 0.1;      // global norm, as released; <= 0 disables
  int64_t warmup_steps = 100;  // linear warm-up of the learning rate from 0
  double ema_sigma_rel = 0.1;  // power EMA, as released
  diffusion::FlowMatchingConfig flow;
  // Largest standard deviation of the Gaussian noise added to the conditioning latent (a level
  // drawn uniformly per clip); 0: clean context, as released.
  double condition_noise = 0;
  // Strength of the motion-weighted loss (diffusion::motion_weight); 0: uniform, as released.
  double motion_weight = 0;
  // Probability per clip of training with zero actions, so that sampling can guide with the
  // difference (infer::SamplerOptions::action_guidance); 0: as released.
  double action_dropout = 0;
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
  // One optimiser step on this process's micro-batches of a step (accumulated, then averaged over
  // the data-parallel ranks, data_parallel.h): each brings its own generator. The statistics are
  // means over the whole global batch.
  struct MicroBatch {
    torch::Tensor x0, actions;
    torch::Generator generator;
  };
  WmStepStats step(const std::vector<MicroBatch>& micro_batches);
  // One optimiser step on any loss of the network (distillation): loss_fn runs the forward pass
  // (the caller picks its precision) and returns a scalar. Learning-rate warm-up, clipping and
  // the EMA update as in step(); WmStepStats::loss and mse are the returned loss.
  WmStepStats step_loss(const std::function<torch::Tensor(models::ActionDitImpl& net)>& loss_fn);
  // The same over `count` micro-batches: loss_fn(net, j) for j < count, each backward pass scaled
  // by 1 / count, gradients then averaged over the data-parallel ranks.
  WmStepStats step_loss(
      const std::function<torch::Tensor(models::ActionDitImpl& net, int64_t micro)>& loss_fn, int64_t count);
  // Flow-matching loss of the EMA network on a fixed batch and fixed noise (no update).
  double eval_loss(const torch::Tensor& x0, const torch::Tensor& actions, uint64_t seed);

  models::ActionDit& net() { return net_; }
  models::ActionDit& ema() { return ema_; }
  int64_t steps_done() const { return steps_; }
  const WmTrainOptions& options() const { return options_; }
  const torch::Device& device() const { return device_; }
  Precision precision() const { return precision_; }

  // Entries merged into the checkpoint's config.json beside the network's: the action
  // normalisation {"actions": {slot: statistics}} run_wm_training gives the network.
  void set_config_extras(nlohmann::json extras) { config_extras_ = std::move(extras); }

  // Checkpoint: model.safetensors holds the EMA weights as "net.*" (what inference loads, as
  // in the released converted checkpoints); trainer_state holds the raw weights, AdamW moments
  // and RNG. Always CPU float32 tensors, whatever the device and precision; resume() loads them
  // onto the trainer's device.
  void save(const std::filesystem::path& dir, const nlohmann::json& extra = nlohmann::json::object()) const;
  void resume(const std::filesystem::path& dir);

  // ZeRO-1 under data parallelism (fused_adamw.h): each rank keeps 1/world of the AdamW moments;
  // the parameters stay bit for bit those of plain data parallelism. Call before resume() (each
  // rank then adopts its slice of the saved moments) and the first step; a world of 1: no change.
  void shard_optimizer_state();
  // Every rank calls it with the --zero1 it was given: the ranks check they agree (a collective),
  // then shard when it is on.
  void apply_zero1(bool requested);
  // Before rank 0 saves a sharded trainer: every rank calls it (a collective) so the checkpoint
  // holds the whole moments. Nothing to do unsharded.
  void gather_optimizer_state();
  // Bytes of AdamW moments this process holds.
  int64_t optimizer_moment_bytes() const { return fused_->moment_elements() * 4; }
  // The last step's gradient buckets and how many of them started during the backward pass
  // (zero buckets: no overlap, a world of 1 or DOJO_DIST_OVERLAP=0).
  OverlappedGradientAverage::Stats overlap_stats() const {
    return overlap_ ? overlap_->last_step() : OverlappedGradientAverage::Stats{};
  }

 private:
  double lr_at(int64_t step) const;

  models::ActionDit net_, ema_;
  WmTrainOptions options_;
  torch::Device device_;
  Precision precision_;
  std::vector<torch::Tensor> params_, ema_params_;
  std::unique_ptr<torch::optim::AdamW> optimizer_;
  std::unique_ptr<FusedAdamW> fused_;  // flat parameters, gradients, moments and EMA over optimizer_
  // Under data parallelism: the gradient all-reduce started during the last backward pass
  // (DOJO_DIST_OVERLAP=0: after it, DataParallel::average_gradients).
  std::unique_ptr<OverlappedGradientAverage> overlap_;
  double ema_gamma_;
  int64_t steps_ = 0;
  nlohmann::json config_extras_ = nlohmann::json::object();
};

enum class WmStage { kPretrain, kPosttrain, kScratch };
WmStage parse_wm_stage(const std::string& text);  // pretrain | posttrain | scratch
std::string to_string(WmStage stage);

// The same network with fresh LoRA adapters (A: PyTorch's Linear init, B: zeros, so its output is
// unchanged) on the layers `lora` names.
models::ActionDit with_lora_adapters(const models::ActionDit& base, const models::LoraConfig& lora);
// Freezes every parameter but the LoRA adapters (and the action MLPs when asked): no gradient, so
// no optimiser state either. Logs the counts as "<who> --lora: ...".
void freeze_all_but_adapters(models::ActionDitImpl& net, bool train_action_mlps, const std::string& who);

struct WmTrainJob {
  WmStage stage = WmStage::kPretrain;
  std::vector<LatentCacheSpec> data;
  // One mixture weight per dataset of `data` (MixtureIndex): dataset d fills weight[d] / sum of
  // each batch whatever its size. Empty: every cached clip alike, as before weights existed.
  std::vector<double> weights;
  std::filesystem::path out;   // out/checkpoint, out/loss.csv, out/latents-<i>.safetensors
  std::filesystem::path init;  // posttrain: the pretrained checkpoint (a post-trained one: continued)
  models::DitConfig model = models::DitConfig::small();
  WmTrainOptions options;
  int batch_size = 8;        // the global batch of a step, over every process
  int64_t accumulate = 1;    // micro-batches per step and process (data_parallel.h)
  int64_t steps = 2000;      // total steps (a resumed job continues up to this)
  double time_budget_s = 0;  // wall-clock budget of the job, latent caching included; 0: none
  int64_t save_every = 100;
  uint64_t seed = 0;
  // Scaling of the robot action dimensions (the datasets' action slots) before the action MLPs,
  // stored in the network's config (models::DitConfig::action_scale) for a fresh or post-trained
  // network: a factor, or with standardize_actions one per dimension that gives the cached
  // chunk-relative deltas unit standard deviation. 1 / false: the released behaviour.
  double action_scale = 1.0;
  bool standardize_actions = false;
  // Post-training with LoRA (rank > 0): adapters on the blocks' attention and MLP layers train with
  // the action MLPs (re-initialised, trained in full); every other weight is frozen: no gradient,
  // no optimiser state, bit for bit the init's in every checkpoint.
  models::LoraConfig lora;
  torch::Device device = torch::kCPU;         // where the network trains (latent caching stays on CPU)
  Precision precision = Precision::kFloat32;  // bf16: autocast forward, float32 master weights
  // > 0: intra-op threads for the training steps, set once the latent caches are ready. Encoding
  // them is convolution-bound and runs on the caller's threads; the steps are matmul-bound
  // (core/runtime.h, matmul_bound_threads).
  int matmul_threads = 0;
  // Activation checkpointing (models::ActionDitImpl::recompute_blocks): less memory, more compute.
  bool checkpoint_activations = false;
  // ZeRO-1 under data parallelism (WmTrainer::shard_optimizer_state); ignored in a world of 1.
  bool zero1 = false;
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

}  // namespace dojo::train
