#include "models/keypoint_probe.h"

#include <torch/torch.h>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/state_dict.h"
#include "io/frame_ops.h"

namespace dojo::models {

namespace nn = torch::nn;

nlohmann::json KeypointProbeConfig::to_json() const {
  return {{"size", size}, {"width", width}, {"keypoints", keypoints}};
}

KeypointProbeConfig KeypointProbeConfig::from_json(const nlohmann::json& j) {
  KeypointProbeConfig c;
  const JsonFields f(j, "keypoint probe config");
  f.get("size", c.size);
  f.get("width", c.width);
  if (j.contains("keypoints")) {
    DOJO_CHECK(j["keypoints"].is_array() && !j["keypoints"].empty(),
               "keypoint probe config: field 'keypoints' must be a non-empty list of names");
    c.keypoints = j["keypoints"].get<std::vector<std::string>>();
  }
  check_positive("keypoint probe config", "size", c.size);
  check_positive("keypoint probe config", "width", c.width);
  DOJO_CHECK(c.size % 8 == 0, "keypoint probe config: field 'size' must be a multiple of 8");
  return c;
}

namespace {

// conv 3x3 (stride) -> SiLU -> conv 3x3 -> SiLU: one stage of the feature pyramid.
void add_stage(nn::Sequential& seq, int64_t in, int64_t out, int64_t stride) {
  seq->push_back(nn::Conv2d(nn::Conv2dOptions(in, out, 3).stride(stride).padding(1)));
  seq->push_back(nn::SiLU());
  seq->push_back(nn::Conv2d(nn::Conv2dOptions(out, out, 3).padding(1)));
  seq->push_back(nn::SiLU());
}

}  // namespace

KeypointProbeImpl::KeypointProbeImpl(KeypointProbeConfig config) : config_(std::move(config)) {
  const int64_t w = config_.width, k = config_.num_keypoints();
  features = nn::Sequential();
  add_stage(features, 3, w, 2);          // S/2
  add_stage(features, w, 2 * w, 2);      // S/4
  add_stage(features, 2 * w, 4 * w, 2);  // S/8
  register_module("features", features);
  heatmaps = register_module("heatmaps", nn::Conv2d(nn::Conv2dOptions(4 * w, k, 1)));
  presence = register_module("presence", nn::Linear(8 * w, k));
}

KeypointOutput KeypointProbeImpl::forward(const torch::Tensor& images) {
  DOJO_CHECK(images.dim() == 4 && images.size(1) == 3 && images.size(2) == config_.size &&
                 images.size(3) == config_.size,
             "keypoint probe: expected images [B, 3, " + std::to_string(config_.size) + ", " +
                 std::to_string(config_.size) + "]");
  const auto f = features->forward(images * 2 - 1);  // [B, 4w, h, w]
  const int64_t B = f.size(0), h = f.size(2), w = f.size(3), K = config_.num_keypoints();
  // Soft-argmax: the expected cell centre under a softmax over each heatmap.
  const auto weights = torch::softmax(heatmaps->forward(f).view({B, K, h * w}), -1).view({B, K, h, w});
  const auto xs = (torch::arange(w, f.options()) + 0.5) / static_cast<double>(w);  // [w]
  const auto ys = (torch::arange(h, f.options()) + 0.5) / static_cast<double>(h);  // [h]
  const auto u = (weights.sum(2) * xs).sum(-1);                                    // [B, K]
  const auto v = (weights.sum(3) * ys).sum(-1);                                    // [B, K]
  KeypointOutput out;
  out.coords = torch::stack({u, v}, -1);                                                  // [B, K, 2]
  const auto pooled = torch::cat({f.mean({2, 3}), std::get<0>(f.flatten(2).max(2))}, 1);  // [B, 8w]
  out.presence = presence->forward(pooled);                                               // [B, K]
  return out;
}

torch::Tensor probe_input(const KeypointProbe& probe, const torch::Tensor& frames_u8) {
  DOJO_CHECK(frames_u8.dim() == 4 && frames_u8.size(3) == 3 && frames_u8.scalar_type() == torch::kUInt8,
             "keypoint probe: frames must be [N, H, W, 3] uint8");
  const int64_t s = probe->config().size;
  auto f = frames_u8;
  if (f.size(1) != s || f.size(2) != s) f = io::resize_center_crop(f, s, s);
  return f.permute({0, 3, 1, 2}).to(torch::kFloat32).div(255.0);  // [N, 3, s, s]
}

KeypointOutput detect_keypoints(KeypointProbe& probe, const torch::Tensor& frames_u8, int64_t batch) {
  torch::NoGradGuard no_grad;
  probe->eval();
  const auto input = probe_input(probe, frames_u8);  // [N, 3, s, s]
  std::vector<torch::Tensor> coords, presence;
  for (int64_t i = 0; i < input.size(0); i += batch) {
    const auto out = probe->forward(input.narrow(0, i, std::min(batch, input.size(0) - i)));
    coords.push_back(out.coords);
    presence.push_back(out.presence);
  }
  return {torch::cat(coords), torch::cat(presence)};
}

int64_t keypoint_offset(const KeypointProbeConfig& config, const std::string& embodiment) {
  const std::string prefix = embodiment == "robot" ? "arm." : embodiment == "human" ? "hand." : "";
  DOJO_CHECK(!prefix.empty(), "keypoint probe: unknown embodiment '" + embodiment + "'");
  for (size_t i = 0; i + 3 <= config.keypoints.size(); ++i)
    if (config.keypoints[i].rfind(prefix, 0) == 0) return static_cast<int64_t>(i);
  throw Error("keypoint probe: no " + prefix + "* keypoints in this probe");
}

torch::Tensor probe_targets(const KeypointProbeConfig& config, const std::vector<std::string>& embodiment,
                            const torch::Tensor& keypoints) {
  const int64_t N = keypoints.size(0);
  DOJO_CHECK(static_cast<int64_t>(embodiment.size()) == N && keypoints.dim() == 3 && keypoints.size(1) == 3,
             "keypoint probe: one embodiment name per [3, 3] keypoint row expected");
  auto target = torch::zeros({N, config.num_keypoints(), 3});  // absent unless set below
  for (int64_t i = 0; i < N; ++i)
    target[i].narrow(0, keypoint_offset(config, embodiment[static_cast<size_t>(i)]), 3).copy_(keypoints[i]);
  return target;
}

CheckpointData keypoint_probe_checkpoint(const KeypointProbeImpl& probe) {
  CheckpointData data;
  data.config = {{"model", "keypoint_probe"}, {"config", probe.config().to_json()}};
  for (const auto& [name, t] : state_dict(probe)) data.model.emplace_back("probe." + name, t);
  return data;
}

KeypointProbe load_keypoint_probe(const std::filesystem::path& dir) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  const auto& cfg = ckpt.config();
  DOJO_CHECK(
      cfg.value("model", std::string()) == "keypoint_probe" && cfg.contains("config"),
      (ckpt.dir() / "config.json").string() + ": not a keypoint probe checkpoint (model != keypoint_probe)");
  KeypointProbe probe(KeypointProbeConfig::from_json(cfg["config"]));
  LoadOptions opts;
  opts.prefix = "probe.";
  load_state_dict(*probe, ckpt.model(), opts);  // strict: a mismatch throws, naming the tensors
  probe->eval();
  return probe;
}

}  // namespace dojo::models
