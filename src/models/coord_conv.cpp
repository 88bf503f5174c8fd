#include "models/coord_conv.h"

#include <torch/torch.h>

#include "core/error.h"
#include "io/frame_ops.h"

namespace dojo::models {

namespace nn = torch::nn;

namespace {

// conv 3x3 (stride 2) -> SiLU -> conv 3x3 -> SiLU.
}  // namespace

torch::Tensor frames_to_unit_images(const torch::Tensor& frames_u8, int64_t size, const std::string& who) {
  DOJO_CHECK(frames_u8.dim() == 4 && frames_u8.size(3) == 3 && frames_u8.scalar_type() == torch::kUInt8,
             who + ": frames must be [N, H, W, 3] uint8");
  auto f = frames_u8;
  if (f.size(1) != size || f.size(2) != size) f = io::resize_center_crop(f, size, size);
  return f.permute({0, 3, 1, 2}).to(torch::kFloat32).div(255.0);  // [N, 3, size, size]
}

void add_conv_stage(nn::Sequential& seq, int64_t in, int64_t out) {
  seq->push_back(nn::Conv2d(nn::Conv2dOptions(in, out, 3).stride(2).padding(1)));
  seq->push_back(nn::SiLU());
  seq->push_back(nn::Conv2d(nn::Conv2dOptions(out, out, 3).padding(1)));
  seq->push_back(nn::SiLU());
}

nn::Sequential coord_conv_features(int64_t width) {
  nn::Sequential features;
  add_conv_stage(features, 3 + 2, width);          // S/2; the pixel's own (x, y) as two more channels
  add_conv_stage(features, width, 2 * width);      // S/4
  add_conv_stage(features, 2 * width, 4 * width);  // S/8
  return features;
}

torch::Tensor with_pixel_coordinates(const torch::Tensor& images) {
  const int64_t B = images.size(0), s = images.size(2);
  const auto grid = torch::linspace(-1, 1, s, images.options());
  const auto gy = grid.view({1, 1, s, 1}).expand({B, 1, s, s}),
             gx = grid.view({1, 1, 1, s}).expand({B, 1, s, s});
  return torch::cat({images * 2 - 1, gx, gy}, 1);  // [B, 5, S, S]
}

std::vector<double> read_config_stats(const nlohmann::json& j, const char* key, int64_t width,
                                      const std::string& who, const std::string& width_name) {
  if (!j.contains(key)) return {};
  const auto& v = j[key];
  DOJO_CHECK(v.is_array() && static_cast<int64_t>(v.size()) == width,
             who + " config: field '" + key + "' must be an array of " + width_name + " numbers");
  std::vector<double> out;
  for (const auto& x : v) {
    DOJO_CHECK(x.is_number(), who + " config: field '" + key + "' must hold numbers");
    out.push_back(x.get<double>());
  }
  return out;
}

torch::Tensor stats_tensor(const std::vector<double>& values, int64_t width, double fill) {
  if (values.empty()) return torch::full({width}, fill);
  return torch::tensor(std::vector<float>(values.begin(), values.end()));
}

}  // namespace dojo::models
