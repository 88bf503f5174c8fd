// Training the success detector (models/success_detector.h) on episodes whose every frame the
// simulator labelled (1: the task is done at that frame). Windows are drawn with balanced
// classes (successes are rare: they sit at the ends of the good episodes), blurred and
// brightened like the keypoint probe's frames so that generated video reads the same.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <optional>

#include "core/autocast.h"
#include "models/success_detector.h"

namespace dojo::train {

// Labelled episodes, one file: "frames" [E, T, H, W, 3] uint8, "labels" [E, T] float (0 / 1),
// "heldout" [E] uint8 (1: never trained on; the accuracy reported is theirs); optionally
// "simulator_frames", as "frames".
struct SuccessData {
  torch::Tensor frames, labels, heldout;
  // DojoSim's frames of the same episodes when `frames` are a world model's replays (else
  // undefined): the detector trained on the replays is also scored on real frames.
  torch::Tensor simulator_frames;  // [E, T, H, W, 3] uint8
  static SuccessData load(
      const std::filesystem::path& path);              // throws dojo::Error naming the file and tensor
  void save(const std::filesystem::path& path) const;  // atomically
};

struct SuccessTrainJob {
  std::filesystem::path data;  // a SuccessData file
  std::filesystem::path out;   // out/checkpoint, out/loss.csv
  models::SuccessDetectorConfig model;
  int batch_size = 32;
  int64_t accumulate = 1;  // micro-batches per step and process (data_parallel.h)
  int64_t steps = 800;     // total (a resumed job continues up to this)
  double time_budget_s = 0;
  int64_t save_every = 200;
  double lr = 2e-3;  // AdamW, linear warm-up over the first 50 steps
  double blur_probability = 0.5;
  double brightness = 0.1;
  uint64_t seed = 0;
  int64_t votes = models::kSuccessVotes;  // windows voting on an episode in the episode-level score
  // Where it trains (the model moves there; draws stay on the CPU) and at what precision (bf16:
  // the forward pass under autocast, weights and checkpoints float32).
  torch::Device device = torch::kCPU;
  Precision precision = Precision::kFloat32;
};

struct SuccessAccuracy {
  double accuracy = 0;           // over every window of the episodes
  double balanced_accuracy = 0;  // mean of the accuracy on success and on failure windows
  int64_t windows = 0, positives = 0;
};

struct SuccessTrainResult {
  int64_t steps = 0;
  double loss = 0;  // mean of the last 20 steps
  SuccessAccuracy train, heldout;
  SuccessAccuracy heldout_episodes;  // per held-out episode: the vote over its last windows vs its outcome
  // The same two on the simulator's frames of the held-out episodes, when the data has them.
  struct Simulated {
    SuccessAccuracy heldout, heldout_episodes;
  };
  std::optional<Simulated> simulator;
  double seconds = 0;
};

// Trains, resuming from out/checkpoint when it exists.
SuccessTrainResult run_success_training(const SuccessTrainJob& job);

// The detector's per-window accuracy on episodes `which` [E] (bool) of `data`.
SuccessAccuracy success_accuracy(models::SuccessDetector& detector, const SuccessData& data,
                                 const torch::Tensor& which);

// Per episode of `which`: temporal voting over its last `votes` windows (models::success_vote,
// as `policy eval` decides an episode) against its label at the last frame. `windows` counts
// the episodes here, `positives` the successful ones.
SuccessAccuracy episode_accuracy(models::SuccessDetector& detector, const SuccessData& data,
                                 const torch::Tensor& which, int64_t votes);

}  // namespace dojo::train
