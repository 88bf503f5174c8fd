#include "models/success_detector.h"

#include <torch/torch.h>

#include <algorithm>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/state_dict.h"
#include "io/frame_ops.h"
#include "models/coord_conv.h"

namespace dojo::models {

namespace nn = torch::nn;

nlohmann::json SuccessDetectorConfig::to_json() const {
  return {{"window", window}, {"stride", stride}, {"size", size}, {"width", width}};
}

SuccessDetectorConfig SuccessDetectorConfig::from_json(const nlohmann::json& j) {
  SuccessDetectorConfig c;
  const JsonFields f(j, "success detector config");
  f.get("window", c.window);
  f.get("stride", c.stride);  // absent in detectors saved before it existed: 1
  f.get("size", c.size);
  f.get("width", c.width);
  check_positive("success detector config", "window", c.window);
  check_positive("success detector config", "stride", c.stride);
  check_positive("success detector config", "size", c.size);
  check_positive("success detector config", "width", c.width);
  DOJO_CHECK(c.size % 8 == 0, "success detector config: field 'size' must be a multiple of 8");
  return c;
}

namespace {

// conv 3x3 (stride 2) -> SiLU -> conv 3x3 -> SiLU.
}  // namespace

SuccessDetectorImpl::SuccessDetectorImpl(SuccessDetectorConfig config) : config_(config) {
  const int64_t w = config_.width;
  features = nn::Sequential();
  add_conv_stage(features, 3 * config_.window, w);  // S/2
  add_conv_stage(features, w, 2 * w);               // S/4
  add_conv_stage(features, 2 * w, 4 * w);           // S/8
  register_module("features", features);
  head = register_module("head", nn::Linear(8 * w, 1));
}

torch::Tensor SuccessDetectorImpl::forward(const torch::Tensor& windows) {
  const int64_t c = 3 * config_.window, s = config_.size;
  DOJO_CHECK(windows.dim() == 4 && windows.size(1) == c && windows.size(2) == s && windows.size(3) == s,
             "success detector: expected windows [B, " + std::to_string(c) + ", " + std::to_string(s) + ", " +
                 std::to_string(s) + "]");
  const auto f = features->forward(windows * 2 - 1);                                      // [B, 4w, s/8, s/8]
  const auto pooled = torch::cat({f.mean({2, 3}), std::get<0>(f.flatten(2).max(2))}, 1);  // [B, 8w]
  return head->forward(pooled).squeeze(1);                                                // [B]
}

torch::Tensor window_ending_at(const SuccessDetectorConfig& config, const torch::Tensor& video, int64_t end) {
  const int64_t first = end - config.span() + 1;
  DOJO_CHECK(first >= 0 && end < video.size(0),
             "success detector: a window ending at frame " + std::to_string(end) + " needs frames " +
                 std::to_string(first) + ".." + std::to_string(end) + " of a video of " +
                 std::to_string(video.size(0)) + " frames");
  return video.narrow(0, first, config.span())
      .slice(0, 0, config.span(), config.stride);  // [window, H, W, 3]
}

torch::Tensor success_input(const SuccessDetector& detector, const torch::Tensor& windows_u8) {
  const int64_t k = detector->config().window, s = detector->config().size;
  DOJO_CHECK(windows_u8.dim() == 5 && windows_u8.size(1) == k && windows_u8.size(4) == 3 &&
                 windows_u8.scalar_type() == torch::kUInt8,
             "success detector: windows must be [N, " + std::to_string(k) + ", H, W, 3] uint8");
  const int64_t N = windows_u8.size(0), H = windows_u8.size(2), W = windows_u8.size(3);
  auto frames = windows_u8.reshape({N * k, H, W, 3});
  if (H != s || W != s) frames = io::resize_center_crop(frames, s, s);
  return frames.view({N, k, s, s, 3})
      .permute({0, 1, 4, 2, 3})
      .reshape({N, 3 * k, s, s})
      .to(torch::kFloat32)
      .div(255.0);  // [N, 3k, s, s]
}

torch::Tensor success_probability(SuccessDetector& detector, const torch::Tensor& windows_u8, int64_t batch) {
  torch::NoGradGuard no_grad;
  detector->eval();
  const auto input = success_input(detector, windows_u8);  // [N, 3k, s, s]
  std::vector<torch::Tensor> out;
  for (int64_t i = 0; i < input.size(0); i += batch)
    out.push_back(torch::sigmoid(detector->forward(input.narrow(0, i, std::min(batch, input.size(0) - i)))));
  return out.empty() ? torch::zeros({0}) : torch::cat(out);
}

double success_vote(SuccessDetector& detector, const torch::Tensor& video_u8, int64_t votes) {
  const int64_t span = detector->config().span();
  DOJO_CHECK(
      video_u8.dim() == 4 && video_u8.size(0) >= span,
      "success detector: a video of at least " + std::to_string(span) + " frames [T, H, W, 3] is needed");
  const int64_t T = video_u8.size(0), n = std::clamp<int64_t>(votes, 1, T - span + 1);
  std::vector<torch::Tensor> windows;
  for (int64_t i = 0; i < n; ++i)
    windows.push_back(window_ending_at(detector->config(), video_u8, T - 1 - i));
  const auto p = success_probability(detector, torch::stack(windows));  // [n]
  return (p > 0.5).to(torch::kFloat64).mean().item<double>();
}

CheckpointData success_detector_checkpoint(const SuccessDetectorImpl& detector) {
  CheckpointData data;
  data.config = {{"model", "success_detector"}, {"config", detector.config().to_json()}};
  for (const auto& [name, t] : state_dict(detector)) data.model.emplace_back("detector." + name, t);
  return data;
}

SuccessDetector load_success_detector(const std::filesystem::path& dir) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  const auto& cfg = ckpt.config();
  DOJO_CHECK(cfg.value("model", std::string()) == "success_detector" && cfg.contains("config"),
             (ckpt.dir() / "config.json").string() +
                 ": not a success detector checkpoint (model != success_detector)");
  SuccessDetector detector(SuccessDetectorConfig::from_json(cfg["config"]));
  LoadOptions opts;
  opts.prefix = "detector.";
  load_state_dict(*detector, ckpt.model(), opts);
  detector->eval();
  return detector;
}

}  // namespace dojo::models
