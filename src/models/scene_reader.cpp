#include "models/scene_reader.h"

#include <torch/torch.h>

#include <cmath>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/state_dict.h"
#include "models/coord_conv.h"

namespace dojo::models {

namespace nn = torch::nn;

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
  c.value_mean = read_config_stats(j, "value_mean", c.outputs, "scene reader", "'outputs'");
  c.value_scale = read_config_stats(j, "value_scale", c.outputs, "scene reader", "'outputs'");
  for (const double v : c.value_scale)
    DOJO_CHECK(std::isfinite(v) && v > 0, "scene reader config: 'value_scale' must be finite and positive");
  return c;
}

SceneReaderImpl::SceneReaderImpl(SceneReaderConfig config) : config_(std::move(config)) {
  const int64_t w = config_.width, cells = (config_.size / 8) * (config_.size / 8);
  features = coord_conv_features(w);
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
  const auto f = features->forward(with_pixel_coordinates(images));  // [B, 4w, s/8, s/8]
  return head->forward(f.flatten(1));                                // [B, outputs]
}

torch::Tensor SceneReaderImpl::normalise(const torch::Tensor& values) const {
  return (values - mean_) / scale_;
}

torch::Tensor SceneReaderImpl::denormalise(const torch::Tensor& values) const {
  return values * scale_ + mean_;
}

torch::Tensor reader_input(const SceneReader& reader, const torch::Tensor& frames_u8) {
  return frames_to_unit_images(frames_u8, reader->config().size, "scene reader");
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
