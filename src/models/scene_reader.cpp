#include "models/scene_reader.h"

#include <torch/torch.h>

#include <cmath>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/state_dict.h"
#include "io/frame_ops.h"

namespace dojo::models {

namespace nn = torch::nn;

namespace {

std::vector<double> read_stats(const nlohmann::json& j, const char* key, int64_t width) {
  if (!j.contains(key)) return {};
  const auto& v = j[key];
  DOJO_CHECK(v.is_array() && static_cast<int64_t>(v.size()) == width,
             std::string("scene reader config: field '") + key + "' must be an array of 'outputs' numbers");
  std::vector<double> out;
  for (const auto& x : v) {
    DOJO_CHECK(x.is_number(), std::string("scene reader config: field '") + key + "' must hold numbers");
    out.push_back(x.get<double>());
  }
  return out;
}

torch::Tensor stats_tensor(const std::vector<double>& v, int64_t width, double fill) {
  if (v.empty()) return torch::full({width}, fill);
  return torch::tensor(std::vector<float>(v.begin(), v.end()));
}

// conv 3x3 (stride 2) -> SiLU -> conv 3x3 -> SiLU.
void add_stage(nn::Sequential& seq, int64_t in, int64_t out) {
  seq->push_back(nn::Conv2d(nn::Conv2dOptions(in, out, 3).stride(2).padding(1)));
  seq->push_back(nn::SiLU());
  seq->push_back(nn::Conv2d(nn::Conv2dOptions(out, out, 3).padding(1)));
  seq->push_back(nn::SiLU());
}

}  // namespace

nlohmann::json SceneReaderConfig::to_json() const {
  nlohmann::json j = {{"size", size}, {"width", width}, {"hidden", hidden}, {"outputs", outputs}};
  if (!value_mean.empty()) j["value_mean"] = value_mean;
  if (!value_scale.empty()) j["value_scale"] = value_scale;
  return j;
}

SceneReaderConfig SceneReaderConfig::from_json(const nlohmann::json& j) {
  SceneReaderConfig c;
  const JsonFields f(j, "scene reader config");
  f.get("size", c.size);
  f.get("width", c.width);
  f.get("hidden", c.hidden);
  f.get("outputs", c.outputs);
  for (const auto& [key, value] : std::initializer_list<std::pair<const char*, int64_t>>{
           {"size", c.size}, {"width", c.width}, {"hidden", c.hidden}, {"outputs", c.outputs}})
    check_positive("scene reader config", key, value);
  DOJO_CHECK(c.size % 8 == 0, "scene reader config: field 'size' must be a multiple of 8");
  c.value_mean = read_stats(j, "value_mean", c.outputs);
  c.value_scale = read_stats(j, "value_scale", c.outputs);
  for (const double v : c.value_scale)
    DOJO_CHECK(std::isfinite(v) && v > 0, "scene reader config: 'value_scale' must be finite and positive");
  return c;
}

SceneReaderImpl::SceneReaderImpl(SceneReaderConfig config) : config_(std::move(config)) {
  const int64_t w = config_.width, cells = (config_.size / 8) * (config_.size / 8);
  features = nn::Sequential();
  add_stage(features, 3 + 2, w);      // S/2; the pixel's own (x, y) as two more channels
  add_stage(features, w, 2 * w);      // S/4
  add_stage(features, 2 * w, 4 * w);  // S/8
  register_module("features", features);
  head = nn::Sequential(nn::Linear(4 * w * cells, config_.hidden), nn::SiLU(),
                        nn::Linear(config_.hidden, config_.outputs));
  register_module("head", head);
  mean_ = register_buffer("value_mean", stats_tensor(config_.value_mean, config_.outputs, 0.0));
  scale_ = register_buffer("value_scale", stats_tensor(config_.value_scale, config_.outputs, 1.0));
}

torch::Tensor SceneReaderImpl::forward(const torch::Tensor& images) {
  const int64_t s = config_.size;
  DOJO_CHECK(images.dim() == 4 && images.size(1) == 3 && images.size(2) == s && images.size(3) == s,
             "scene reader: expected images [B, 3, " + std::to_string(s) + ", " + std::to_string(s) + "]");
  const int64_t B = images.size(0);
  const auto grid = torch::linspace(-1, 1, s, images.options());
  const auto gy = grid.view({1, 1, s, 1}).expand({B, 1, s, s}),
             gx = grid.view({1, 1, 1, s}).expand({B, 1, s, s});
  const auto f = features->forward(torch::cat({images * 2 - 1, gx, gy}, 1));  // [B, 4w, s/8, s/8]
  return head->forward(f.flatten(1));                                         // [B, outputs]
}

torch::Tensor SceneReaderImpl::normalise(const torch::Tensor& values) const {
  return (values - mean_) / scale_;
}

torch::Tensor SceneReaderImpl::denormalise(const torch::Tensor& values) const {
  return values * scale_ + mean_;
}

torch::Tensor reader_input(const SceneReader& reader, const torch::Tensor& frames_u8) {
  DOJO_CHECK(frames_u8.dim() == 4 && frames_u8.size(3) == 3 && frames_u8.scalar_type() == torch::kUInt8,
             "scene reader: frames must be [N, H, W, 3] uint8");
  const int64_t s = reader->config().size;
  auto f = frames_u8;
  if (f.size(1) != s || f.size(2) != s) f = io::resize_center_crop(f, s, s);
  return f.permute({0, 3, 1, 2}).to(torch::kFloat32).div(255.0);  // [N, 3, s, s]
}

std::vector<double> read_scene(SceneReader& reader, const torch::Tensor& frame_u8) {
  torch::NoGradGuard no_grad;
  reader->eval();
  const auto values = reader->denormalise(reader->forward(reader_input(reader, frame_u8.unsqueeze(0))))[0].to(
      torch::kFloat64);
  return std::vector<double>(values.data_ptr<double>(), values.data_ptr<double>() + values.numel());
}

CheckpointData scene_reader_checkpoint(const SceneReaderImpl& reader) {
  CheckpointData data;
  data.config = {{"model", "scene_reader"}, {"config", reader.config().to_json()}};
  for (const auto& [name, t] : state_dict(reader)) data.model.emplace_back("reader." + name, t);
  return data;
}

SceneReader load_scene_reader(const std::filesystem::path& dir) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  const auto& cfg = ckpt.config();
  const auto file = (ckpt.dir() / "config.json").string();
  DOJO_CHECK(cfg.contains("model") && cfg["model"] == "scene_reader" && cfg.contains("config"),
             file + ": not a scene reader checkpoint (model != scene_reader)");
  SceneReaderConfig config;
  try {
    config = SceneReaderConfig::from_json(cfg["config"]);
  } catch (const Error& e) {
    throw Error(file + ": " + e.what());
  }
  SceneReader reader(config);
  LoadOptions opts;
  opts.prefix = "reader.";
  load_state_dict(*reader, ckpt.model(), opts);
  reader->eval();
  return reader;
}

}  // namespace dojo::models
