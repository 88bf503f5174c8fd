// Value model for planning (recipes/planning.h): from a window of the last 4 frames, how far the
// next subtask boundary is, as a fraction of `horizon` control steps (0: at the boundary, 1: as
// far as `horizon` or more). Lower is better. DojoSim's boundaries are simulator events of the bin
// task (sim::bin_task_stage: reach, lift, over the bin, release).
//
// The backbone is pluggable: any network from a window [B, 3 window, S, S] in [0, 1] to one logit
// per window; the one trained here is the success detector's network (models/success_detector.h:
// three stride-2 conv stages, pooled, one linear head) at window 4, the value being the logit's
// sigmoid. The paper's backbone (DINOv2) is not available here.
#pragma once

#include <cstdint>
#include <filesystem>
#include <vector>

#include "models/success_detector.h"

namespace dojo::models {

struct ValueModel {
  SuccessDetector network{nullptr};  // the backbone and its head
  int64_t horizon = 32;              // control steps a value of 1 stands for

  int64_t window() const { return network->config().window; }
};

// A new value model (window 4, consecutive frames).
ValueModel make_value_model(int64_t horizon = 32);

// Values in [0, 1] of every window of a video [T, H, W, 3] uint8 (T >= window), in eval mode:
// [T - window + 1], the window ending at frame window - 1 first.
std::vector<double> window_values(ValueModel& model, const torch::Tensor& video_u8);

// One value for a predicted video from its window values: the mean of the values from the first
// window up to the dip after which they rise again (past a boundary the next subtask's values
// start high), so a video that gets close to its next boundary scores low. Lowest wins. Throws
// dojo::Error on an empty list.
double video_value(const std::vector<double>& window_values, double rise = 0.1);

// Checkpoint directory: config.json {"model": "value_model", "config": {backbone..., "horizon"}},
// weights as "value.<name>".
CheckpointData value_model_checkpoint(const ValueModel& model);
ValueModel load_value_model(const std::filesystem::path& dir);  // throws dojo::Error naming the file

}  // namespace dojo::models
