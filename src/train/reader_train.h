// Training the scene reader (models/scene_reader.h) on frames labelled with what a vision-only bin
// policy needs to know (sim/bin_belief.h's values, from simulator state). Snapshots at chosen
// steps are kept: a reader that reads worse drives a worse policy, which is how the reader
// policies of policy evaluation are graded.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <vector>

#include "models/scene_reader.h"

namespace dojo::train {

// Labelled frames, one file: "frames" [N, H, W, 3] uint8, "values" [N, V] float (raw units),
// "heldout" [N] uint8 (1: frames of held-out episodes, never trained on).
struct SceneReadings {
  torch::Tensor frames, values, heldout;
  static SceneReadings load(const std::filesystem::path& path);  // throws dojo::Error naming file and tensor
  void save(const std::filesystem::path& path) const;            // atomically
};

struct ReaderTrainJob {
  std::filesystem::path data;  // a SceneReadings file
  std::filesystem::path out;   // out/checkpoint, out/snapshots/step-NNNNNN, out/loss.csv
  models::SceneReaderConfig model;
  int batch_size = 64;
  int64_t accumulate = 1;
  int64_t steps = 2000;
  int64_t save_every = 500;
  std::vector<int64_t> snapshots = {100, 300, 800};  // kept besides the final one
  double lr = 1e-3;                                  // AdamW, warm-up over 50 steps, cosine decay to a tenth
  double blur_probability = 0.5, brightness = 0.1;   // generated video is softer
  uint64_t seed = 0;
};

// How far a reader's values are from the truth on some frames: the object's and the bin's centre
// (mean distance, cm), the grasp height (mean absolute, cm), and the share of frames whose
// object-in-bin call (sim::BinBelief::object_in_bin) is right.
struct ReaderErrors {
  int64_t frames = 0;
  double object_cm = 0, bin_cm = 0, grasp_height_cm = 0, in_bin_accuracy = 0;
};

struct ReaderTrainResult {
  int64_t steps = 0;
  double loss = 0;  // mean of the last 20 steps (normalised values, squared)
  ReaderErrors heldout;
  std::vector<std::filesystem::path> snapshots;  // out/snapshots/step-NNNNNN, by step
  double seconds = 0;
};

// Trains, resuming from out/checkpoint when it exists.
ReaderTrainResult run_reader_training(const ReaderTrainJob& job);

// The errors of `reader` on frames `which` [N] (bool) of `data`.
ReaderErrors reader_errors(models::SceneReader& reader, const SceneReadings& data,
                           const torch::Tensor& which);

}  // namespace dojo::train
