// A small streaming decoder for the tokenizer's 16-channel latents, in the TAEHV style: per latent
// frame, convolutions at the latent resolution, then stages that upsample (nearest, 2x) and grow
// time (one latent -> 2 -> 4 frames), each stage's memory blocks seeing their own input of the
// previous frame. The first latent's 4 frames are trimmed to 1, so latents [1 + k] give 1 + 4k
// frames like the Wan decoder. Trained by distillation from the Wan decoder on the tokenizer's
// latents (train/fast_decoder_train.h); the Wan decoder stays the quality path.
//
// Why our own: the streaming engine spends most of a step decoding (4 frames of the Wan decoder at
// 64x64 cost ~3x the student's 4 denoising hops on 2 cores); no packaged decoder reads our latents.
#pragma once

#include <torch/nn/module.h>
#include <torch/nn/modules/container/modulelist.h>
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

struct FastDecoderConfig {
  int64_t latent_channels = 16;
  // Channels and memory blocks of the three stages: latent resolution (1 frame per latent),
  // 2x (2 frames), 4x (4 frames); then 8x with `head_width` channels to RGB.
  std::vector<int64_t> widths = {64, 48, 32};
  std::vector<int64_t> blocks = {2, 1, 1};
  int64_t head_width = 16;
  nlohmann::json to_json() const;
  static FastDecoderConfig from_json(const nlohmann::json& j);  // throws dojo::Error naming the field
};

// y = ReLU(conv2(ReLU(conv1([x, x_prev]))) + x): sees the previous frame's input at this block.
class MemoryBlockImpl : public torch::nn::Module {
 public:
  explicit MemoryBlockImpl(int64_t channels);
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& past);  // [B, C, H, W] each
  torch::nn::Conv2d conv1{nullptr}, conv2{nullptr};
};
TORCH_MODULE(MemoryBlock);

// Per-block memory of one stream: the previous frame's input of every memory block.
struct FastDecoderState {
  std::vector<torch::Tensor> past;  // one per block, in visiting order; undefined = zeros
  int64_t latents_seen = 0;
  void clear() { past.clear(), latents_seen = 0; }
};

class FastDecoderImpl : public torch::nn::Module {
 public:
  explicit FastDecoderImpl(FastDecoderConfig config = {});
  // One latent frame z [B, 16, h, w] (normalised, as the DiT produces them) -> its frames
  // [B, 3, n, 8h, 8w] in [-1, 1]: n = 1 for a stream's first latent, else 4.
  torch::Tensor step(const torch::Tensor& z, FastDecoderState& state);
  // Latents [B, 16, T, h, w] -> [B, 3, 1 + 4 (T − 1), 8h, 8w], one fresh stream.
  torch::Tensor decode(const torch::Tensor& z);
  const FastDecoderConfig& config() const { return config_; }

  torch::nn::Conv2d input{nullptr}, head1{nullptr}, head2{nullptr};
  torch::nn::ModuleList stages{nullptr};  // per stage: its memory blocks
  torch::nn::ModuleList grow{nullptr};    // 1x1 convs: stage s width -> 2 x stage s + 1 width

 private:
  FastDecoderConfig config_;
};
TORCH_MODULE(FastDecoder);

// Checkpoint directory: config.json {"model": "fast_decoder", "config": ...}, weights "decoder.*".
CheckpointData fast_decoder_checkpoint(const FastDecoderImpl& decoder);
FastDecoder load_fast_decoder(const std::filesystem::path& dir);  // in eval mode

}  // namespace dojo::models
