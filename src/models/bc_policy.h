// Behaviour-cloning policy: from the newest camera frame and the command in force (its own last
// command: the only proprioception a state-free policy has), a chunk of the next commands. The
// same network drives the robot in DojoSim and in the world model, because it never sees
// simulator state (eval/policy_eval.h). Trained by train/bc_train.h on scripted demonstrations;
// its snapshots along training are policies of graded quality.
//
// Layout: frame [B, 3, S, S] in [0, 1], with each pixel's (x, y) as two more channels -> three
// stride-2 stages of 3x3 convolutions (S/8 x S/8) -> the feature map flattened, not pooled (where
// the object lies is what reaching needs, and pooling would throw it away) -> with the normalised
// last command, an MLP -> the chunk as offsets from the last command, in units of the
// demonstrations' per-dimension step size [B, chunk, A]. The chunk is longer than a decision's 4
// commands (only those are executed): predicting where the arm will be 16 steps on makes the
// network find the object it reaches for, which the next few steps alone barely depend on.
#pragma once

#include <torch/nn/module.h>
#include <torch/nn/modules/container/sequential.h>
#include <torch/nn/modules/conv.h>
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

struct BcPolicyConfig {
  int64_t size = 64;       // frames are resized to size x size (a multiple of 8)
  int64_t width = 32;      // channels of the first stage; doubled at each of the next two
  int64_t hidden = 256;    // MLP width
  int64_t action_dim = 6;  // the embodiment's command width
  int64_t chunk = 16;      // commands predicted at once (a decision executes the first few)
  // Normalisation, measured on the demonstrations: commands as (c - mean) / scale, offsets from
  // the last command as d / step. Empty: identity (an untrained policy).
  std::vector<double> command_mean, command_scale, step_scale;

  nlohmann::json to_json() const;
  static BcPolicyConfig from_json(const nlohmann::json& j);  // throws dojo::Error naming the field
};

class BcPolicyImpl : public torch::nn::Module {
 public:
  explicit BcPolicyImpl(BcPolicyConfig config = {});
  // images [B, 3, size, size] in [0, 1], last commands [B, A] (normalised) -> offsets
  // [B, chunk, A] in step units.
  torch::Tensor forward(const torch::Tensor& images, const torch::Tensor& last_normalised);

  // Raw units <-> the network's units, with the config's statistics.
  torch::Tensor normalise_command(const torch::Tensor& command) const;         // [..., A]
  torch::Tensor offsets_to_commands(const torch::Tensor& offsets,              // [B, chunk, A]
                                    const torch::Tensor& last_command) const;  // [B, A] raw -> raw
  torch::Tensor commands_to_offsets(const torch::Tensor& commands,             // [B, chunk, A] raw
                                    const torch::Tensor& last_command) const;  // -> step units

  const BcPolicyConfig& config() const { return config_; }
  torch::nn::Sequential features{nullptr};
  torch::nn::Sequential head{nullptr};

 private:
  BcPolicyConfig config_;
  torch::Tensor mean_, scale_, step_;  // [A] buffers from the config
};
TORCH_MODULE(BcPolicy);

// uint8 frames [N, H, W, 3] of any size -> the policy's input [N, 3, size, size] in [0, 1].
torch::Tensor bc_input(const BcPolicy& policy, const torch::Tensor& frames_u8);

// One decision in eval mode: frame [H, W, 3] uint8, last command [A] raw -> commands [chunk, A] raw.
torch::Tensor bc_act(BcPolicy& policy, const torch::Tensor& frame_u8, const torch::Tensor& last_command);

// Checkpoint directory: config.json {"model": "bc_policy", "config": ...}, weights as "policy.<name>".
CheckpointData bc_policy_checkpoint(const BcPolicyImpl& policy);
BcPolicy load_bc_policy(const std::filesystem::path& dir);

}  // namespace dojo::models
