// What the frame-reading models that must know where things are (the behaviour-cloning policy,
// models/bc_policy.h; the scene reader, models/scene_reader.h) share: uint8 frames to their input,
// each pixel's (x, y) as two more channels, three stride-2 stages of 3x3 convolutions to an S/8
// feature map that they flatten (not pool: position is the output), and the normalisation
// statistics their configs carry.
#pragma once

#include <torch/nn/modules/container/sequential.h>
#include <torch/types.h>

#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace dojo::models {

// uint8 frames [N, H, W, 3] of any size -> [N, 3, size, size] in [0, 1] (resized and centre-cropped
// when needed); `who` starts the error message.
torch::Tensor frames_to_unit_images(const torch::Tensor& frames_u8, int64_t size, const std::string& who);

// The three stages for images with their coordinate channels: [B, 3 + 2, S, S] -> [B, 4 width, S/8, S/8].
torch::nn::Sequential coord_conv_features(int64_t width);
// One stage of the frame encoders: a stride-2 3x3 convolution in -> out, SiLU, a 3x3 convolution
// out -> out, SiLU (the success detector stacks the same stages on stacked frames).
void add_conv_stage(torch::nn::Sequential& seq, int64_t in, int64_t out);
// images [B, 3, S, S] in [0, 1] -> [B, 5, S, S]: the image in [-1, 1], then x and y in [-1, 1].
torch::Tensor with_pixel_coordinates(const torch::Tensor& images);

// A config's statistics field `key`: absent -> empty; else `width` numbers. Throws dojo::Error
// "WHO config: field 'KEY' must be an array of WIDTH_NAME numbers" / "... must hold numbers".
std::vector<double> read_config_stats(const nlohmann::json& j, const char* key, int64_t width,
                                      const std::string& who, const std::string& width_name);
// The statistics as a [width] tensor; `fill` everywhere when there are none (an untrained model).
torch::Tensor stats_tensor(const std::vector<double>& values, int64_t width, double fill);

}  // namespace dojo::models
