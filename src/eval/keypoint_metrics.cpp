#include "eval/keypoint_metrics.h"

#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/error.h"
#include "data/clip_loader.h"

namespace dojo::eval {

double detection_radius_px(int64_t height, int64_t width) {
  return kDetectionRadiusPx64 * static_cast<double>(std::min(height, width)) / 64.0;
}

KeypointScores score_keypoints(const models::KeypointOutput& pred, int64_t offset, const torch::Tensor& truth,
                               int64_t height, int64_t width) {
  const int64_t T = truth.size(0);
  DOJO_CHECK(truth.dim() == 3 && truth.size(2) == 3 && pred.coords.size(0) == T,
             "keypoint scores: expected [T, K, 3] ground truth for the T frames the probe read");
  const int64_t K = truth.size(1);
  const auto coords = pred.coords.narrow(1, offset, K).to(torch::kFloat64);         // [T, K, 2]
  const auto found = pred.presence.narrow(1, offset, K).gt(0).to(torch::kFloat64);  // [T, K]
  const auto gt = truth.to(torch::kFloat64);
  const auto in_view = gt.select(2, 2);  // [T, K]
  const auto du = (coords.select(2, 0) - gt.select(2, 0)) * static_cast<double>(width);
  const auto dv = (coords.select(2, 1) - gt.select(2, 1)) * static_cast<double>(height);
  const auto dist = (du.pow(2) + dv.pow(2)).sqrt();  // [T, K] pixels
  const auto count = in_view.sum(1);                 // [T]
  const auto error = ((dist * in_view).sum(1) / count.clamp_min(1)).contiguous();
  const auto near = dist.le(detection_radius_px(height, width)).to(torch::kFloat64);  // [T, K]
  const auto detected = ((found * near * in_view).sum(1) / count.clamp_min(1)).contiguous();
  const auto present = ((found * in_view).sum(1) / count.clamp_min(1)).contiguous();
  KeypointScores s;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (int64_t t = 0; t < T; ++t) {
    const bool any = count[t].item<double>() > 0;
    s.error.push_back(any ? error[t].item<double>() : nan);
    s.detected.push_back(any ? detected[t].item<double>() : nan);
    s.present.push_back(any ? present[t].item<double>() : nan);
  }
  return s;
}

nlohmann::json ProbeAccuracy::to_json() const {
  return {{"frames", frames},
          {"error_px", error_px},
          {"recall", recall},
          {"recall_within_radius", recall_within_radius},
          {"false_positive", false_positive}};
}

ProbeAccuracy probe_accuracy(models::KeypointProbe& probe, const std::vector<std::filesystem::path>& datasets,
                             const std::string& split) {
  const auto& config = probe->config();
  const auto data = data::load_keypoint_frames(datasets, split, config.size);
  const auto target = models::probe_targets(config, data.embodiment, data.keypoints);  // [N, K, 3]
  const auto out = models::detect_keypoints(probe, data.frames);
  const auto present = target.select(2, 2).gt(0.5), found = out.presence.gt(0);  // [N, K]
  const auto dist = ((out.coords - target.narrow(2, 0, 2)) * static_cast<double>(config.size)).norm(2, 2);
  ProbeAccuracy a;
  a.frames = data.frames.size(0);
  a.error_px = dist.masked_select(present).mean().item<double>();
  a.recall = found.masked_select(present).to(torch::kFloat64).mean().item<double>();
  const auto near = dist.le(detection_radius_px(config.size, config.size));
  a.recall_within_radius =
      found.logical_and(near).masked_select(present).to(torch::kFloat64).mean().item<double>();
  a.false_positive = found.masked_select(present.logical_not()).to(torch::kFloat64).mean().item<double>();
  return a;
}

double nan_mean(const std::vector<double>& values) {
  double sum = 0;
  int64_t n = 0;
  for (double v : values)
    if (!std::isnan(v)) sum += v, ++n;
  return n > 0 ? sum / static_cast<double>(n) : std::numeric_limits<double>::quiet_NaN();
}

}  // namespace dojo::eval
