// Scene reader: from one camera frame, the numbers a vision-only bin policy plans with (the
// object's position and grasp, the bin's position: sim/bin_belief.h's BinBelief as values). It is
// the perception half of the "reader" policies of policy evaluation (recipes/vision_policies.h);
// trained by train/reader_train.h on DojoSim frames labelled from simulator state.
//
// Layout: frame [B, 3, S, S] in [0, 1] with each pixel's (x, y) as two more channels -> three
// stride-2 stages of 3x3 convolutions (S/8 x S/8) -> flattened (where things are is the output)
// -> MLP -> [B, outputs] in normalised units ((value - mean) / scale, measured on the training set).
#pragma once

#include <torch/nn/module.h>
#include <torch/nn/modules/container/sequential.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <vector>

namespace dojo {
struct CheckpointData;
}

namespace dojo::models {

struct SceneReaderConfig {
  int64_t size = 64;     // frames are resized to size x size (a multiple of 8)
  int64_t width = 16;    // channels of the first stage; doubled at each of the next two
  int64_t hidden = 128;  // MLP width
  int64_t outputs = 8;   // values read
  // Normalisation of the outputs, measured on the training frames. Empty: identity.
  std::vector<double> value_mean, value_scale;

  nlohmann::json to_json() const;
  static SceneReaderConfig from_json(const nlohmann::json& j);  // throws dojo::Error naming the field
};

class SceneReaderImpl : public torch::nn::Module {
 public:
  explicit SceneReaderImpl(SceneReaderConfig config = {});
  // images [B, 3, size, size] in [0, 1] -> normalised values [B, outputs].
  torch::Tensor forward(const torch::Tensor& images);
  torch::Tensor normalise(const torch::Tensor& values) const;    // raw [..., outputs] -> normalised
  torch::Tensor denormalise(const torch::Tensor& values) const;  // normalised -> raw

  const SceneReaderConfig& config() const { return config_; }
  torch::nn::Sequential features{nullptr};
  torch::nn::Sequential head{nullptr};

 private:
  SceneReaderConfig config_;
  torch::Tensor mean_, scale_;  // [outputs] buffers from the config
};
TORCH_MODULE(SceneReader);

// uint8 frames [N, H, W, 3] of any size -> the reader's input [N, 3, size, size] in [0, 1].
torch::Tensor reader_input(const SceneReader& reader, const torch::Tensor& frames_u8);

// Reads one frame in eval mode: [H, W, 3] uint8 -> raw values [outputs] (float64).
std::vector<double> read_scene(SceneReader& reader, const torch::Tensor& frame_u8);

// Checkpoint directory: config.json {"model": "scene_reader", "config": ...}, weights "reader.<name>".
CheckpointData scene_reader_checkpoint(const SceneReaderImpl& reader);
SceneReader load_scene_reader(const std::filesystem::path& dir);  // throws dojo::Error naming the file

}  // namespace dojo::models
