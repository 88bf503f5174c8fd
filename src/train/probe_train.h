// Training the keypoint probe (models/keypoint_probe.h) on DojoSim episodes, whose simulator
// records where every keypoint of the embodiment is in each frame. Robot frames teach the arm's
// keypoints and are negatives for the hand's; human frames the other way round. Blur and
// brightness augmentation keep the probe reading generated frames, which are softer than the
// renders it learns from.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "core/autocast.h"
#include "models/keypoint_probe.h"

namespace dojo::train {

struct ProbeTrainJob {
  std::vector<std::filesystem::path> datasets;  // episode stores with keypoints (dojo sim generate)
  std::string split = "train";
  std::filesystem::path out;  // out/checkpoint, out/loss.csv
  models::KeypointProbeConfig model;
  int batch_size = 32;
  int64_t accumulate = 1;  // micro-batches per step and process (data_parallel.h)
  int64_t steps = 1500;    // total (a resumed job continues up to this)
  double time_budget_s = 0;
  int64_t save_every = 250;
  double lr = 2e-3;               // AdamW, linear warm-up over the first 50 steps
  double blur_probability = 0.5;  // per frame: Gaussian blur with sigma ~ U(0.3, 1.5) px
  double brightness = 0.1;        // per frame: add U(-b, b)
  uint64_t seed = 0;
  // Where it trains (the model moves there; draws stay on the CPU) and at what precision (bf16:
  // the forward pass under autocast, weights and checkpoints float32).
  torch::Device device = torch::kCPU;
  Precision precision = Precision::kFloat32;
};

struct ProbeTrainResult {
  int64_t steps = 0;
  double loss = 0;  // mean of the last 20 steps
  double seconds = 0, frames_per_second = 0;
};

// Trains, resuming from out/checkpoint when it exists.
ProbeTrainResult run_probe_training(const ProbeTrainJob& job);

// The probe's loss on a batch: L1 of the coordinates of present keypoints (in units of the frame
// size, weighted 10) plus the presence cross-entropy. images [B, 3, S, S], target [B, K, 3].
torch::Tensor keypoint_probe_loss(const models::KeypointOutput& out, const torch::Tensor& target);

}  // namespace dojo::train
