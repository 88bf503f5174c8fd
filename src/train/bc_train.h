// Training the behaviour-cloning policy (models/bc_policy.h) on demonstrations: episodes of
// frames, the command in force at each frame and the demonstrator's command after seeing it.
// Snapshots at chosen steps are kept as inference checkpoints: a partly trained policy is a
// policy of lower quality, which is what policy evaluation needs many of.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <vector>

#include "core/autocast.h"
#include "models/bc_policy.h"

namespace dojo::train {

// Demonstrations, one file: "frames" [E, T, H, W, 3] uint8; "executed" [E, T, A] the command in
// force at each frame (what the robot was last told: the policy's proprioception); "labels"
// [E, T, A] the demonstrator's command after seeing frame t (with noise injected into the
// executed commands, the labels stay the clean ones, so the policy learns to recover);
// "heldout" [E] uint8 (1: never trained on).
struct Demonstrations {
  torch::Tensor frames, executed, labels, heldout;
  static Demonstrations load(const std::filesystem::path& path);  // throws dojo::Error naming file and tensor
  void save(const std::filesystem::path& path) const;             // atomically
};

struct BcTrainJob {
  std::filesystem::path data;  // a Demonstrations file
  std::filesystem::path out;   // out/checkpoint, out/snapshots/step-NNNNNN, out/loss.csv
  models::BcPolicyConfig model;
  int batch_size = 64;
  int64_t accumulate = 1;  // micro-batches per step and process (data_parallel.h)
  int64_t steps = 3000;    // total (a resumed job continues up to this)
  double time_budget_s = 0;
  int64_t save_every = 500;
  std::vector<int64_t> snapshots = {200, 500, 1000};  // kept besides the final one
  double lr = 1e-3;  // AdamW, linear warm-up over 50 steps, cosine decay to a tenth
  double blur_probability = 0.5;
  double brightness = 0.1;
  // Random translation in pixels (pad and crop). 0 by default: the camera is fixed and commands
  // are absolute joint targets, so a shifted frame teaches a wrong target (4 px is ~4 cm here).
  int64_t shift = 0;
  uint64_t seed = 0;
  // Where it trains (the model moves there; draws stay on the CPU) and at what precision (bf16:
  // the forward pass under autocast, weights and checkpoints float32).
  torch::Device device = torch::kCPU;
  Precision precision = Precision::kFloat32;
};

struct BcTrainResult {
  int64_t steps = 0;
  double loss = 0;                               // mean of the last 20 steps (offsets in step units, squared)
  double heldout_loss = 0;                       // the same on the held-out episodes, without augmentation
  std::vector<std::filesystem::path> snapshots;  // every snapshot in out/snapshots, by step
  double seconds = 0;
};

// Trains, resuming from out/checkpoint when it exists.
BcTrainResult run_bc_training(const BcTrainJob& job);

// Mean squared offset error of `policy` on episodes `which` [E] (bool) of `data`.
double bc_loss(models::BcPolicy& policy, const Demonstrations& data, const torch::Tensor& which);

}  // namespace dojo::train
