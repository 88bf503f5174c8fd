// Success detector: a small convolutional classifier that tells from the last few frames whether
// the task is done (for DojoSim's bin task: the object lies in the bin, at rest, released). The
// simulator labels every frame it renders, so it trains on DojoSim frames alone; policy
// evaluation then reads success off generated video, where no simulator state exists
// (eval/policy_eval.h). A sibling of the keypoint probe.
//
// Layout: a window of `window` frames stacked on channels [B, 3 window, S, S] in [0, 1] -> three
// stride-2 stages of 3x3 convolutions -> mean and max pooled features -> one logit (> 0: success).
// Temporal voting over the last windows of an episode decides the episode (success_vote).
#pragma once

#include <torch/nn/module.h>
#include <torch/nn/modules/container/sequential.h>
#include <torch/nn/modules/linear.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>

namespace dojo {
struct CheckpointData;
}

namespace dojo::models {

struct SuccessDetectorConfig {
  int64_t window = 3;  // frames one decision sees (motion tells "at rest" from "falling")
  int64_t stride = 1;  // frames between them: > 1 spans more of the episode with the same input
  int64_t size = 64;   // frames are resized to size x size (a multiple of 8)
  int64_t width = 24;  // channels of the first stage; doubled at each of the next two

  int64_t span() const { return (window - 1) * stride + 1; }  // video frames one window covers

  nlohmann::json to_json() const;
  static SuccessDetectorConfig from_json(const nlohmann::json& j);  // throws dojo::Error naming the field
};

class SuccessDetectorImpl : public torch::nn::Module {
 public:
  explicit SuccessDetectorImpl(SuccessDetectorConfig config = {});
  // windows [B, 3 window, size, size] float in [0, 1] -> logits [B].
  torch::Tensor forward(const torch::Tensor& windows);

  const SuccessDetectorConfig& config() const { return config_; }
  torch::nn::Sequential features{nullptr};
  torch::nn::Linear head{nullptr};

 private:
  SuccessDetectorConfig config_;
};
TORCH_MODULE(SuccessDetector);

// The window of `video` [T, H, W, 3] that ends at frame `end`: frames end - (window - 1) stride,
// ..., end, [window, H, W, 3].
torch::Tensor window_ending_at(const SuccessDetectorConfig& config, const torch::Tensor& video, int64_t end);
// uint8 windows [N, window, H, W, 3] of any frame size -> the detector's input [N, 3 window, S, S].
torch::Tensor success_input(const SuccessDetector& detector, const torch::Tensor& windows_u8);
// Success probabilities [N] of uint8 windows [N, window, H, W, 3], in eval mode, batched.
torch::Tensor success_probability(SuccessDetector& detector, const torch::Tensor& windows_u8,
                                  int64_t batch = 64);
// Temporal voting over the end of a video [T, H, W, 3] uint8 (T >= span): the last `votes`
// windows (ending at T-1, T-2, ...) each vote success when their probability exceeds 0.5; the
// result is the share of windows that voted success, in [0, 1] (an episode succeeds above 0.5).
inline constexpr int64_t kSuccessVotes = 5;  // windows voting on an episode (policy eval, held-out scores)
double success_vote(SuccessDetector& detector, const torch::Tensor& video_u8, int64_t votes = kSuccessVotes);

// Checkpoint directory: config.json {"model": "success_detector", "config": ...}, weights as
// "detector.<name>".
CheckpointData success_detector_checkpoint(const SuccessDetectorImpl& detector);
SuccessDetector load_success_detector(const std::filesystem::path& dir);

}  // namespace dojo::models
