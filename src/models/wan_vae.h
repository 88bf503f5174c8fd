// Wan2.1 causal video VAE (the DreamDojo tokenizer): 8x spatial, 4x temporal compression,
// 16 latent channels, T_lat = 1 + (T - 1) / 4. Module and parameter names equal the released
// PyTorch state dict (a converted Wan2.1_VAE.pth loads as is). Facts: ../shared/reference/wan_vae.md.
//
// Two equivalent ways to run the causal model:
//  - chunked (the released call sequence): encode frame 0, then chunks of 4 frames, decode one
//    latent frame at a time, with per-layer feature caches (WanVaeCache) carried between calls.
//    WanVaeStreamEncoder / WanVaeStreamDecoder wrap this for streams of any length with bounded
//    memory.
//  - whole-clip: the full sequence in one pass with zero left padding, where the temporal
//    resamplers treat frame 0 specially exactly as the caches do. Faster for training; tested to
//    equal the chunked path.
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <vector>

namespace dojo {
struct CheckpointData;
}

namespace dojo::models {

struct WanVaeConfig {
  int64_t dim = 96;                                             // base width
  int64_t z_dim = 16;                                           // latent channels
  std::vector<int64_t> dim_mult = {1, 2, 4, 4};                 // width multipliers per stage
  int64_t num_res_blocks = 2;                                   // encoder blocks per stage (decoder: +1)
  std::vector<double> attn_scales = {};                         // resolution scales with attention
  std::vector<bool> temperal_downsample = {false, true, true};  // (sic, released spelling)
  double dropout = 0.0;
  // Per-channel latent normalisation z = (mu - mean) / std (published constants by default).
  std::vector<double> latent_mean = {-0.7571, -0.7089, -0.9113, 0.1075,  -0.1745, 0.9653,  -0.1517, 1.5508,
                                     0.4134,  -0.0715, 0.5517,  -0.3632, -0.1922, -0.9497, 0.2503,  -0.2921};
  std::vector<double> latent_std = {2.8184, 1.4541, 2.3275, 2.6558, 1.2196, 1.7708, 2.6052, 2.0743,
                                    3.2687, 2.1526, 2.8652, 1.5579, 1.6382, 1.1253, 2.8251, 1.9160};

  // dim 8: the golden-fixture size (~0.46 M parameters).
  static WanVaeConfig tiny();
  // Spatial / temporal compression factors implied by the config.
  int64_t spatial_factor() const;
  int64_t temporal_factor() const;

  nlohmann::json to_json() const;
  // Accepts the released constructor kwargs (missing keys keep defaults); throws dojo::Error
  // naming the field on a bad value.
  static WanVaeConfig from_json(const nlohmann::json& j);
};

// Frame-count helpers (temporal factor 4).
inline int64_t wan_latent_frames(int64_t pixel_frames) { return 1 + (pixel_frames - 1) / 4; }
inline int64_t wan_pixel_frames(int64_t latent_frames) { return 1 + 4 * (latent_frames - 1); }

// Feature caches of one encoder or decoder stream: one slot per cached layer, visited in a
// fixed order each chunk (CACHE_T = 2 frames). Slots start empty; upsample3d marks its slot
// "Rep" after the first chunk.
struct WanVaeCache {
  enum class State { kEmpty, kRep, kTensor };
  struct Slot {
    State state = State::kEmpty;
    torch::Tensor x;
  };
  std::vector<Slot> slots;
  size_t next_slot = 0;

  void clear() {
    slots.clear();
    next_slot = 0;
  }
  void begin_chunk() { next_slot = 0; }
  Slot& next() {
    if (next_slot >= slots.size()) slots.resize(next_slot + 1);
    return slots[next_slot++];
  }
  int64_t bytes() const;
};

// --- building blocks (names follow the released module) --------------------------------------

// Conv3d with causal time padding (2 * p_t frames on the left, none on the right) and symmetric
// spatial padding; an optional cache of previous input frames replaces the left zero padding.
class CausalConv3dImpl : public torch::nn::Module {
 public:
  CausalConv3dImpl(int64_t in, int64_t out, std::vector<int64_t> kernel,
                   std::vector<int64_t> stride = {1, 1, 1}, std::vector<int64_t> padding = {0, 0, 0});
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& cache = {});  // [B, C, T, H, W]
  void reset_parameters();

  torch::Tensor weight, bias;
  std::vector<int64_t> kernel, stride, padding;
};
TORCH_MODULE(CausalConv3d);

// true: CausalConv3d always pads and runs the full kernel (the plain reference); false (default):
// a lone frame with no cache skips the all-zero past taps. Tests check both agree.
bool& conv3d_reference_path();

// x / ||x||_2 (over channels) * sqrt(C) * gamma.
class RmsNormImpl : public torch::nn::Module {
 public:
  RmsNormImpl(int64_t dim, bool images);
  torch::Tensor forward(const torch::Tensor& x);  // [B, C, ...]
  torch::Tensor gamma;
  double scale;
};
TORCH_MODULE(RmsNorm);

class ResidualBlockImpl : public torch::nn::Module {
 public:
  ResidualBlockImpl(int64_t in, int64_t out, double dropout);
  torch::Tensor forward(const torch::Tensor& x, WanVaeCache* cache);

  torch::nn::ModuleList residual{nullptr};
  RmsNorm norm1{nullptr}, norm2{nullptr};
  CausalConv3d conv1{nullptr}, conv2{nullptr}, shortcut{nullptr};
  double dropout;
};
TORCH_MODULE(ResidualBlock);

// Single-head self-attention over the H*W tokens of each frame.
class AttentionBlockImpl : public torch::nn::Module {
 public:
  explicit AttentionBlockImpl(int64_t dim);
  torch::Tensor forward(const torch::Tensor& x);  // [B, C, T, H, W]

  RmsNorm norm{nullptr};
  torch::nn::Conv2d to_qkv{nullptr}, proj{nullptr};
};
TORCH_MODULE(AttentionBlock);

class ResampleImpl : public torch::nn::Module {
 public:
  enum class Mode { kUpsample2d, kUpsample3d, kDownsample2d, kDownsample3d };
  ResampleImpl(int64_t dim, Mode mode);
  torch::Tensor forward(const torch::Tensor& x, WanVaeCache* cache);

  Mode mode;
  torch::nn::ModuleList resample{nullptr};  // 0: parameter-free pad / upsample, 1: Conv2d
  torch::nn::Conv2d conv{nullptr};
  CausalConv3d time_conv{nullptr};
};
TORCH_MODULE(Resample);

// Encoder3d and Decoder3d share the layout: conv1, a stage list, middle, head.
class WanCoderImpl : public torch::nn::Module {
 public:
  WanCoderImpl(const WanVaeConfig& c, bool decoder);
  // cache == nullptr: whole-clip path.
  torch::Tensor forward(const torch::Tensor& x, WanVaeCache* cache);

  bool is_decoder;
  CausalConv3d conv1{nullptr};
  torch::nn::ModuleList stages{nullptr};  // "downsamples" or "upsamples"
  torch::nn::ModuleList middle{nullptr}, head{nullptr};
  RmsNorm head_norm{nullptr};
  CausalConv3d head_conv{nullptr};
};
TORCH_MODULE(WanCoder);

struct WanVaeEncoding {
  torch::Tensor mu, log_var;  // [B, z_dim, T_lat, H/8, W/8]
};

class WanVaeImpl : public torch::nn::Module {
 public:
  explicit WanVaeImpl(WanVaeConfig config = {});

  // Encoder body on one chunk with caches (nullptr: a whole clip). [B,3,T,H,W] -> [B,2z,T',h,w]
  torch::Tensor encoder_forward(const torch::Tensor& x, WanVaeCache* cache);
  // x in [-1, 1], T = 1 + 4k. chunked=true: the released chunk sequence 1, 4, 4, ...
  WanVaeEncoding encode(const torch::Tensor& x, bool chunked = true);
  // The encoder-head output before conv1 (for parity checks).
  torch::Tensor encode_head(const torch::Tensor& x, bool chunked = true);
  // Unnormalised latents -> pixels (unclamped). chunked=true: one latent frame per call.
  torch::Tensor decode(const torch::Tensor& mu, bool chunked = true);
  // Decoder body on latent frames already passed through conv2.
  torch::Tensor decoder_forward(const torch::Tensor& x, WanVaeCache* cache);

  // z = (mu - mean) * (1 / std), and the inverse, as the released wrapper computes them.
  torch::Tensor normalize(const torch::Tensor& mu) const;
  torch::Tensor denormalize(const torch::Tensor& z) const;
  // Released WanVAE.encode / decode: normalised latents; decode is clamped to [-1, 1].
  torch::Tensor encode_latents(const torch::Tensor& x) { return normalize(encode(x).mu); }
  torch::Tensor decode_latents(const torch::Tensor& z) { return decode(denormalize(z)).clamp(-1, 1); }

  const WanVaeConfig& config() const { return config_; }
  // Replaces the normalisation constants (e.g. fitted to a small model's own latents).
  void set_latent_stats(std::vector<double> mean, std::vector<double> std) {
    config_.latent_mean = std::move(mean);
    config_.latent_std = std::move(std);
  }

  WanCoder encoder{nullptr};
  CausalConv3d conv1{nullptr}, conv2{nullptr};
  WanCoder decoder{nullptr};

 private:
  WanVaeConfig config_;
};
TORCH_MODULE(WanVae);

// Initialisation for training from scratch that makes a fresh model act frame by frame: the past
// taps of every causal 3x3x3 conv are zero, temporal downsampling keeps the later frame of each
// pair and temporal upsampling repeats each frame. Single-frame (image) training then carries over
// to video unchanged, and video training starts from "reconstruct each kept frame" instead of
// from random temporal mixing. Spatial weights keep their default initialisation.
void init_frame_by_frame(WanVae& vae);

// Incremental encoder: push pixel frames in any grouping; latents come out as soon as their
// chunk (frame 0, then every 4 frames) is complete. Memory is bounded by the caches.
class WanVaeStreamEncoder {
 public:
  explicit WanVaeStreamEncoder(WanVae vae) : vae_(std::move(vae)) {}
  // frames [B, 3, n, H, W] -> mu of the completed latent frames [B, z, k, h, w] (k may be 0).
  torch::Tensor push(const torch::Tensor& frames);
  void reset();
  const WanVaeCache& cache() const { return cache_; }

 private:
  WanVae vae_;
  WanVaeCache cache_;
  torch::Tensor pending_;  // frames of the current incomplete chunk
  int64_t frames_seen_ = 0;
};

// Incremental decoder: one latent frame in, 1 (first) or 4 pixel frames out.
class WanVaeStreamDecoder {
 public:
  explicit WanVaeStreamDecoder(WanVae vae) : vae_(std::move(vae)) {}
  // mu [B, z, k, h, w] (unnormalised) -> pixels [B, 3, n, H, W], unclamped.
  torch::Tensor push(const torch::Tensor& mu);
  void reset() { cache_.clear(); }
  const WanVaeCache& cache() const { return cache_; }

 private:
  WanVae vae_;
  WanVaeCache cache_;
};

// --- inputs and checkpoints -----------------------------------------------------------------------

// The tokenizer's input layout: uint8 clips [B, T, H, W, 3] -> [B, 3, T, H, W] float32 in [-1, 1],
// and back (clamped, rounded).
torch::Tensor video_to_model(const torch::Tensor& u8);
torch::Tensor model_to_video(const torch::Tensor& x);

// The round trip of video through the chunked inference path, decoding the posterior mean:
// [B, 3, T, H, W] in [-1, 1] (T = 1 + 4k) -> the same, clamped to [-1, 1]. No gradient.
torch::Tensor reconstruct(WanVae& vae, const torch::Tensor& video);
// The same for uint8 frames [B, 1 + 4k, H, W, 3] -> uint8 of the same shape, on the input's device.
torch::Tensor reconstruct_frames(WanVae& vae, const torch::Tensor& video_u8);

// Checkpoint directory (core/checkpoint.h): config.json holds {"model": "wan21_vae", "config":
// WanVaeConfig}, model.safetensors the released WanVAE_ state-dict names. No trainer state.
CheckpointData tokenizer_checkpoint(const WanVaeImpl& vae);
void save_tokenizer(const std::filesystem::path& dir, const WanVaeImpl& vae);
// A checkpoint as written by save_tokenizer (with or without trainer state), in eval mode.
WanVae load_tokenizer(const std::filesystem::path& dir);

}  // namespace dojo::models
