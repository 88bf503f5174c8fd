// Training the value model (models/value_model.h) on episodes whose every frame is labelled with
// the control steps to the next subtask boundary (recipes/planning.h makes them in DojoSim).
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>

#include "models/value_model.h"

namespace dojo::train {

// One file: "frames" [E, T, H, W, 3] uint8, "steps_to_boundary" [E, T] float (control steps from
// each frame to the episode's next subtask boundary; 0 once the task is done, the horizon when no
// boundary is ahead), "heldout" [E] uint8.
struct ValueData {
  torch::Tensor frames, steps_to_boundary, heldout;
  static ValueData load(const std::filesystem::path& path);  // throws dojo::Error naming file and tensor
  void save(const std::filesystem::path& path) const;        // atomically
};

struct ValueTrainJob {
  std::filesystem::path data, out;  // out/checkpoint, out/loss.csv
  int64_t horizon = 32;
  int batch_size = 64;
  int64_t accumulate = 1;
  int64_t steps = 1500;
  int64_t save_every = 500;
  double lr = 1e-3;
  double blur_probability = 0.5, brightness = 0.1;  // generated video is softer
  uint64_t seed = 0;
};

// Held-out quality: the mean absolute error in control steps (targets capped at the horizon) and
// how often, of two windows of one episode 8 steps apart before the same boundary, the later one
// (closer to it) gets the lower value.
struct ValueErrors {
  int64_t windows = 0;
  double mean_abs_steps = 0, order_accuracy = 0;
};

struct ValueTrainResult {
  int64_t steps = 0;
  double loss = 0;
  ValueErrors heldout;
  double seconds = 0;
};

ValueTrainResult run_value_training(const ValueTrainJob& job);  // resumes from out/checkpoint
ValueErrors value_errors(models::ValueModel& model, const ValueData& data, const torch::Tensor& which);

}  // namespace dojo::train
