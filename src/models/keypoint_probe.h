// Keypoint probe: a small convolutional network that finds the embodiment in a frame. It predicts
// the image positions of the robot arm's gripper, wrist and elbow and of the human hand's palm,
// index finger and thumb, each with a presence logit (is that point visible in this frame?).
// Trained on DojoSim frames labelled by the simulator (train/probe_train.h), it turns generated
// video into numbers: where the arm is, and whether it is there at all (eval/wm_eval.h). Policy
// evaluation's success detector and planning's value model are its siblings.
//
// Layout: frames [B, 3, S, S] in [0, 1] -> three stride-2 stages of 3x3 convolutions (S/8 x S/8
// features) -> per keypoint a heatmap whose spatial softmax gives the expected position
// (soft-argmax: sub-cell precision, differentiable) and, from pooled features, a presence logit.
#pragma once

#include <torch/nn/module.h>
#include <torch/nn/modules/container/sequential.h>
#include <torch/nn/modules/conv.h>
#include <torch/nn/modules/linear.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace dojo {
struct CheckpointData;
}

namespace dojo::models {

struct KeypointProbeConfig {
  int64_t size = 64;   // frames are resized to size x size (a multiple of 8)
  int64_t width = 32;  // channels of the first stage; doubled at each of the next two
  // Keypoint names in output order: the robot arm's three, then the human hand's three.
  std::vector<std::string> keypoints = {"arm.gripper", "arm.wrist",  "arm.elbow",
                                        "hand.palm",   "hand.index", "hand.thumb"};

  int64_t num_keypoints() const { return static_cast<int64_t>(keypoints.size()); }
  nlohmann::json to_json() const;
  static KeypointProbeConfig from_json(const nlohmann::json& j);  // throws dojo::Error naming the field
};

struct KeypointOutput {
  torch::Tensor coords;    // [B, K, 2] (u, v) in [0, 1] over the frame (u right, v down)
  torch::Tensor presence;  // [B, K] logits: > 0 means "this keypoint is visible"
};

class KeypointProbeImpl : public torch::nn::Module {
 public:
  explicit KeypointProbeImpl(KeypointProbeConfig config = {});
  // images [B, 3, size, size] float in [0, 1].
  KeypointOutput forward(const torch::Tensor& images);

  const KeypointProbeConfig& config() const { return config_; }
  torch::nn::Sequential features{nullptr};
  torch::nn::Conv2d heatmaps{nullptr};
  torch::nn::Linear presence{nullptr};

 private:
  KeypointProbeConfig config_;
};
TORCH_MODULE(KeypointProbe);

// uint8 frames [N, H, W, 3] of any size -> the probe's input [N, 3, size, size] in [0, 1]
// (centre crop to square, bilinear resize).
torch::Tensor probe_input(const KeypointProbe& probe, const torch::Tensor& frames_u8);

// Runs the probe on uint8 frames [N, H, W, 3] in eval mode, `batch` frames at a time.
KeypointOutput detect_keypoints(KeypointProbe& probe, const torch::Tensor& frames_u8, int64_t batch = 64);

// Index of the first of the embodiment's three keypoints in the probe's output: 0 for "robot", 3
// for "human". Throws dojo::Error for another name or a probe without those keypoints.
int64_t keypoint_offset(const KeypointProbeConfig& config, const std::string& embodiment);

// The probe's targets [N, K, 3] (u, v, present) for frames whose own embodiment's keypoints are
// `keypoints` [N, 3, 3]: those land in the embodiment's three slots, every other keypoint is absent.
torch::Tensor probe_targets(const KeypointProbeConfig& config, const std::vector<std::string>& embodiment,
                            const torch::Tensor& keypoints);

// Checkpoint directory: config.json {"model": "keypoint_probe", "config": ...}, weights as
// "probe.<name>".
CheckpointData keypoint_probe_checkpoint(const KeypointProbeImpl& probe);
KeypointProbe load_keypoint_probe(const std::filesystem::path& dir);

}  // namespace dojo::models
