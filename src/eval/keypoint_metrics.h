// Action following, measured where the embodiment is: the keypoint probe (models/keypoint_probe.h)
// reads generated frames, and its keypoints are compared with the simulator's ground truth of the
// same time step. PSNR cannot tell a rollout that erases the arm from one that moves it where the
// actions send it; the keypoint error and the detection rate can.
#pragma once

#include <torch/types.h>

#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "models/keypoint_probe.h"

namespace dojo::eval {

// A keypoint counts as detected when the probe says it is present and places it within this
// many pixels of the truth at 64x64 (scaled with the frame's shorter side): a presence score alone
// says nothing about where the probe put the point.
constexpr double kDetectionRadiusPx64 = 3.0;
double detection_radius_px(int64_t height, int64_t width);

// Per-frame scores of one video; NaN at frames where no ground-truth keypoint is in view.
struct KeypointScores {
  std::vector<double> error;     // mean distance (pixels at the frame size) of in-view keypoints
  std::vector<double> detected;  // share of in-view keypoints found within detection_radius_px
  std::vector<double> present;   // share of in-view keypoints with a presence logit > 0, anywhere
};

// pred: the probe's output on T frames of size height x width; `offset` selects the embodiment's
// three keypoints in it (models::keypoint_offset); truth [T, 3, 3] (u, v, in_view) from the
// simulator at the same frames.
KeypointScores score_keypoints(const models::KeypointOutput& pred, int64_t offset, const torch::Tensor& truth,
                               int64_t height, int64_t width);

// The probe on held-out real frames of episode stores with simulator keypoints (the split of each):
// how far its keypoints are from the truth and how well it tells present from absent ones.
struct ProbeAccuracy {
  int64_t frames = 0;
  double error_px = 0;              // mean distance of present keypoints, pixels at the probe's size
  double recall = 0;                // present keypoints found (presence logit > 0), anywhere
  double recall_within_radius = 0;  // found within detection_radius_px of the truth
  double false_positive = 0;        // absent keypoints (the other embodiment's, or out of view) "found"
  nlohmann::json to_json() const;
};
ProbeAccuracy probe_accuracy(models::KeypointProbe& probe, const std::vector<std::filesystem::path>& datasets,
                             const std::string& split);

// Mean of the non-NaN values (NaN when there are none).
double nan_mean(const std::vector<double>& values);

}  // namespace dojo::eval
