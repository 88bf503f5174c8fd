// Teacher inference: the tokenizer and the action-conditioned DiT together turn a frame and a
// sequence of actions into video. One chunk = 1 conditioning frame + 12 predicted frames
// (4 latent frames); longer rollouts chain chunks autoregressively, each conditioned on the
// last frame the previous chunk produced (decoded to uint8 and re-encoded, as in the release).
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <filesystem>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>

#include "core/autocast.h"
#include "diffusion/samplers.h"
#include "models/dit.h"
#include "models/wan_vae.h"

namespace dojo::infer {

struct SamplerOptions {
  int steps = 35;  // as released
  double shift = 5.0;
  diffusion::Solver solver = diffusion::Solver::kUniPC;
  // Action guidance: v = v(no actions) + g·(v(actions) − v(no actions)), for networks trained
  // with action dropout; 1 = the plain conditional velocity (one network call per step).
  double action_guidance = 1.0;
};
diffusion::Solver parse_solver(const std::string& text);  // unipc | euler

// How chunks are joined. The release keeps frames [0, 12) of every chunk after the first, so the
// re-decoded conditioning frame repeats and prediction k >= 13 shows ground-truth time k - 1;
// aligned keeps frames [1, 13) so prediction k shows time k (DreamDojo decision table, row 5).
enum class ConcatMode { kAligned, kReleased };
ConcatMode parse_concat_mode(const std::string& text);  // aligned | released

// The prompt embedding the released model cross-attends to (the release embeds its prompt once
// with its text encoder and feeds the result to every call): a safetensors file holding one
// tensor "context", or a .pt / .pth torch.save file holding one tensor (as the released empty-
// prompt embedding asset), [L, C] or [1, L, C] -> [1, L, C] float32. Throws dojo::Error naming the file.
// Without one, models run on a zero context [1, 1, C]: what every DojoSim model is trained with.
torch::Tensor load_text_context(const std::filesystem::path& file);

// Both networks live on `device`. With precision bf16 (or fp16, CUDA only) the DiT's velocity
// calls run under autocast; the tokenizer runs in float32. Inputs may be on any device; outputs
// come back on the CPU.
class WorldModel {
 public:
  WorldModel(models::ActionDit net, models::WanVae tokenizer, torch::Device device = torch::kCPU,
             Precision precision = Precision::kFloat32);
  // A world-model checkpoint and the tokenizer it was trained with, with what its config.json
  // records of its training: the time shift (trained_sampler) and the action ranges.
  static WorldModel load(const std::filesystem::path& checkpoint, const std::filesystem::path& tokenizer,
                         torch::Device device = torch::kCPU, Precision precision = Precision::kFloat32);

  // Replaces the zero text context with `context` [1, L, C] (load_text_context); C must be the
  // network's crossattn_emb_channels (throws dojo::Error naming `source` otherwise).
  void set_text_context(const torch::Tensor& context, const std::string& source = "text context");

  // cond: [B, H, W, 3] uint8, actions: [B, 12, 384] -> [B, 13, H, W, 3] uint8. Frame 0 is the
  // tokenizer's reconstruction of cond. Noise is drawn from `seed` (same seed, same video).
  torch::Tensor predict_chunk(const torch::Tensor& cond, const torch::Tensor& actions, uint64_t seed,
                              const SamplerOptions& sampler = {});

  // first: [B, H, W, 3] uint8, actions: [B, 12 K, 384] -> [B, 1 + 12 K, H, W, 3] uint8.
  // Chunk k uses seed + k. `on_chunk(k)` is called after each chunk.
  torch::Tensor rollout(const torch::Tensor& first, const torch::Tensor& actions, uint64_t seed,
                        const SamplerOptions& sampler = {}, ConcatMode concat = ConcatMode::kAligned,
                        const std::function<void(int64_t)>& on_chunk = {});

  // The tokenizer round trip of single frames: [B, H, W, 3] -> [B, H, W, 3] uint8.
  torch::Tensor reconstruct_frames(const torch::Tensor& frames);
  // The tokenizer round trip of whole videos, encoded and decoded causally in one pass:
  // [B, 1 + 4k, H, W, 3] -> the same shape, uint8.
  torch::Tensor reconstruct_video(const torch::Tensor& video);
  // The tokenizer round trip of a ground-truth rollout, cut and joined exactly as rollout() cuts
  // and joins its chunks (each 1 + 12 frames encoded and decoded on its own): what a rollout
  // would show if the DiT predicted every latent perfectly. [B, 1 + 12 K, H, W, 3] uint8.
  torch::Tensor reconstruct_chunks(const torch::Tensor& video, ConcatMode concat = ConcatMode::kAligned);

  models::ActionDit& net() { return net_; }
  models::WanVae& tokenizer() { return tokenizer_; }
  const torch::Device& device() const { return device_; }
  Precision precision() const { return precision_; }
  // The sampler the network was trained for: the checkpoint's "sampler" entry (the training time
  // shift), else the SamplerOptions defaults.
  const SamplerOptions& trained_sampler() const { return trained_sampler_; }
  // The network's own action normalisation, {slot: statistics} (the checkpoint's "actions" entry;
  // empty for older checkpoints): robot actions are normalised with its range for the dataset's
  // slot, not with the dataset's own statistics.
  const nlohmann::json& action_ranges() const { return action_ranges_; }
  static constexpr int64_t kChunkActions = 12;

 private:
  models::ActionDit net_;
  models::WanVae tokenizer_;
  torch::Device device_;
  Precision precision_;
  SamplerOptions trained_sampler_;
  nlohmann::json action_ranges_ = nlohmann::json::object();
  torch::Tensor text_context_;  // [1, L, C] on device_; undefined: zeros
};

}  // namespace dojo::infer
