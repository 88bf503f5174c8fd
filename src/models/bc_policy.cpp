#include "models/bc_policy.h"

#include <torch/torch.h>

#include <cmath>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/state_dict.h"
#include "models/coord_conv.h"

namespace dojo::models {

namespace nn = torch::nn;

nlohmann::json BcPolicyConfig::to_json() const {
  nlohmann::json j = {
      {"size", size}, {"width", width}, {"hidden", hidden}, {"action_dim", action_dim}, {"chunk", chunk}};
  if (!command_mean.empty()) j["command_mean"] = command_mean;
  if (!command_scale.empty()) j["command_scale"] = command_scale;
  if (!step_scale.empty()) j["step_scale"] = step_scale;
  return j;
}

BcPolicyConfig BcPolicyConfig::from_json(const nlohmann::json& j) {
  BcPolicyConfig c;
  const JsonFields f(j, "bc policy config");
  f.get("size", c.size);
  f.get("width", c.width);
  f.get("hidden", c.hidden);
  f.get("action_dim", c.action_dim);
  f.get("chunk", c.chunk);
  for (const auto& [key, value] :
       std::initializer_list<std::pair<const char*, int64_t>>{{"size", c.size},
                                                              {"width", c.width},
                                                              {"hidden", c.hidden},
                                                              {"action_dim", c.action_dim},
                                                              {"chunk", c.chunk}})
    check_positive("bc policy config", key, value);
  DOJO_CHECK(c.size % 8 == 0, "bc policy config: field 'size' must be a multiple of 8");
  c.command_mean = read_config_stats(j, "command_mean", c.action_dim, "bc policy", "action_dim");
  c.command_scale = read_config_stats(j, "command_scale", c.action_dim, "bc policy", "action_dim");
  c.step_scale = read_config_stats(j, "step_scale", c.action_dim, "bc policy", "action_dim");
  for (const auto* scale : {&c.command_scale, &c.step_scale})
    for (const double v : *scale)
      DOJO_CHECK(std::isfinite(v) && v > 0, "bc policy config: scales must be finite and positive");
  return c;
}

BcPolicyImpl::BcPolicyImpl(BcPolicyConfig config) : config_(std::move(config)) {
  const int64_t w = config_.width, A = config_.action_dim, cells = (config_.size / 8) * (config_.size / 8);
  features = coord_conv_features(w);
  register_module("features", features);
  head = nn::Sequential(nn::Linear(4 * w * cells + A, config_.hidden), nn::SiLU(),
                        nn::Linear(config_.hidden, config_.hidden), nn::SiLU(),
                        nn::Linear(config_.hidden, config_.chunk * A));
  register_module("head", head);
  mean_ = register_buffer("command_mean", stats_tensor(config_.command_mean, A, 0.0));
  scale_ = register_buffer("command_scale", stats_tensor(config_.command_scale, A, 1.0));
  step_ = register_buffer("step_scale", stats_tensor(config_.step_scale, A, 1.0));
}

torch::Tensor BcPolicyImpl::forward(const torch::Tensor& images, const torch::Tensor& last_normalised) {
  const int64_t s = config_.size, A = config_.action_dim;
  DOJO_CHECK(images.dim() == 4 && images.size(1) == 3 && images.size(2) == s && images.size(3) == s,
             "bc policy: expected images [B, 3, " + std::to_string(s) + ", " + std::to_string(s) + "]");
  DOJO_CHECK(
      last_normalised.dim() == 2 && last_normalised.size(0) == images.size(0) && last_normalised.size(1) == A,
      "bc policy: expected last commands [B, " + std::to_string(A) + "]");
  const int64_t B = images.size(0);
  const auto f = features->forward(with_pixel_coordinates(images));  // [B, 4w, s/8, s/8]
  const auto x = torch::cat({f.flatten(1), last_normalised}, 1);     // [B, 4w (s/8)^2 + A]
  return head->forward(x).view({B, config_.chunk, A});               // [B, chunk, A]
}

torch::Tensor BcPolicyImpl::normalise_command(const torch::Tensor& command) const {
  return (command - mean_) / scale_;
}

torch::Tensor BcPolicyImpl::offsets_to_commands(const torch::Tensor& offsets,
                                                const torch::Tensor& last_command) const {
  return last_command.unsqueeze(1) + offsets * step_;  // [B, chunk, A]
}

torch::Tensor BcPolicyImpl::commands_to_offsets(const torch::Tensor& commands,
                                                const torch::Tensor& last_command) const {
  return (commands - last_command.unsqueeze(1)) / step_;  // [B, chunk, A]
}

torch::Tensor bc_input(const BcPolicy& policy, const torch::Tensor& frames_u8) {
  return frames_to_unit_images(frames_u8, policy->config().size, "bc policy");
}

torch::Tensor bc_act(BcPolicy& policy, const torch::Tensor& frame_u8, const torch::Tensor& last_command) {
  torch::NoGradGuard no_grad;
  policy->eval();
  const auto last = last_command.to(torch::kFloat32).reshape({1, -1});  // [1, A]
  const auto offsets =
      policy->forward(bc_input(policy, frame_u8.unsqueeze(0)), policy->normalise_command(last));
  return policy->offsets_to_commands(offsets, last)[0];  // [chunk, A]
}

CheckpointData bc_policy_checkpoint(const BcPolicyImpl& policy) {
  CheckpointData data;
  data.config = {{"model", "bc_policy"}, {"config", policy.config().to_json()}};
  for (const auto& [name, t] : state_dict(policy)) data.model.emplace_back("policy." + name, t);
  return data;
}

BcPolicy load_bc_policy(const std::filesystem::path& dir) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  const auto& cfg = ckpt.config();
  const auto file = (ckpt.dir() / "config.json").string();
  DOJO_CHECK(cfg.contains("model") && cfg["model"] == "bc_policy" && cfg.contains("config"),
             file + ": not a policy checkpoint (model != bc_policy)");
  BcPolicyConfig config;
  try {
    config = BcPolicyConfig::from_json(cfg["config"]);
  } catch (const Error& e) {
    throw Error(file + ": " + e.what());
  }
  BcPolicy policy(config);
  LoadOptions opts;
  opts.prefix = "policy.";
  load_state_dict(*policy, ckpt.model(), opts);
  policy->eval();
  return policy;
}

}  // namespace dojo::models
