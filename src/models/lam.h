// Latent action model (LAM): a spatio-temporal Transformer VAE that turns a pair of consecutive
// frames into a continuous latent action (32-d), trained by reconstructing the second frame from
// the first frame plus the latent. Same structure and parameter names as the released LAM
// (LAM_400k.ckpt, keys "lam.*"): load the checkpoint with LoadOptions{prefix = "lam."}.
// Reference: ../shared/reference/latent_action_model.md.
#pragma once
#include <torch/torch.h>

#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>

namespace dojo {
struct CheckpointData;
}

namespace dojo::models {

struct LamConfig {
  int64_t in_dim = 3;        // image channels
  int64_t model_dim = 1024;  // Transformer width
  int64_t latent_dim = 32;   // latent action size
  int64_t patch_size = 16;
  int64_t enc_blocks = 24;
  int64_t dec_blocks = 24;
  int64_t num_heads = 16;
  double dropout = 0.0;
  // Input frame size the model is trained/used at (frames are resized/cropped to it by callers).
  int64_t height = 240;
  int64_t width = 320;

  int64_t patch_dim() const { return in_dim * patch_size * patch_size; }
  int64_t head_dim() const { return model_dim / num_heads; }

  static LamConfig released();  // 1024 wide, 24 + 24 blocks, 16 heads, patch 16, 240x320
  static LamConfig tiny();      // the golden fixture's: 64 wide, 2 + 2 blocks, 4 heads, patch 8, 48x64
  static LamConfig small();     // trains on 2 CPU cores: 128 wide, 3 + 3 blocks, patch 8, 48x64

  nlohmann::json to_json() const;
  // Missing fields keep their released defaults; wrong types or invalid values throw dojo::Error.
  static LamConfig from_json(const nlohmann::json& j);
  void validate() const;
};

// "b t (hn hp) (wn wp) c -> b t (hn wn) (hp wp c)"; H and W are first cropped to multiples of size.
torch::Tensor lam_patchify(const torch::Tensor& videos, int64_t size);  // [B, T, H, W, C] -> [B, T, N, P]
// Inverse of lam_patchify for an uncropped h_out x w_out frame (h_out, w_out multiples of size).
torch::Tensor lam_unpatchify(const torch::Tensor& patches, int64_t size, int64_t h_out,
                             int64_t w_out);  // [B, T, N, P] -> [B, T, H, W, C]
// Fixed sinusoidal table [len, dim], interleaved: pe[p, 2i] = sin(p w_i), pe[p, 2i+1] = cos(p w_i).
torch::Tensor lam_sinusoidal_table(int64_t len, int64_t dim);

// Rotary position embedding over the sequence axis (dim -2), interleaved pairs (2j, 2j+1),
// frequencies 10000^(-2j/dim) held in the (frozen) parameter "freqs" as in the checkpoint.
struct LamRotaryImpl : torch::nn::Module {
  explicit LamRotaryImpl(int64_t dim);
  torch::Tensor rotate(const torch::Tensor& x) const;  // [..., N, dim] -> same
  torch::Tensor freqs;                                 // [dim / 2]
};
TORCH_MODULE(LamRotary);

// LayerNorm computed in float32 whatever its input, the result in the input's dtype: under
// autocast the linear layers hand it bf16, which libtorch 1.13's CPU kernel refuses beside
// float32 weights (CUDA autocast runs layer_norm in float32 too). Float32 input: torch's own.
struct LamLayerNormImpl : torch::nn::LayerNormImpl {
  explicit LamLayerNormImpl(int64_t dim) : torch::nn::LayerNormImpl(torch::nn::LayerNormOptions({dim})) {}
  torch::Tensor forward(const torch::Tensor& x) {
    return torch::nn::LayerNormImpl::forward(x.to(torch::kFloat32)).to(x.scalar_type());
  }
};
TORCH_MODULE(LamLayerNorm);

// Multi-head self-attention: to_q/to_k/to_v without bias, to_out = (Linear, Dropout).
struct LamSelfAttentionImpl : torch::nn::Module {
  LamSelfAttentionImpl(int64_t dim, int64_t heads, double dropout, bool rotary);
  torch::Tensor forward(const torch::Tensor& x);  // [N, L, E] -> [N, L, E]
  // Attention over axis 1 for every (g, r): [G, L, R, E] -> [G, L, R, E], the numbers forward()
  // gives on x.transpose(1, 2).reshape({G R, L, E}), transposed back. Float32 on the CPU with a
  // short axis: the fused kernel (models/lam_kernels.h), without the transposes.
  torch::Tensor forward_along_axis1(const torch::Tensor& x);
  // [..., E] -> [..., 3E]: q, k and v side by side, from one product.
  torch::Tensor project_qkv(const torch::Tensor& x);
  int64_t heads;
  torch::nn::Linear to_q{nullptr}, to_k{nullptr}, to_v{nullptr};
  torch::nn::Sequential to_out{nullptr};
  LamRotary rotary_embedding{nullptr};
};
TORCH_MODULE(LamSelfAttention);

// Pre-norm block: spatial attention per frame, temporal attention per token (rotary), FFN.
struct LamSpatioTemporalBlockImpl : torch::nn::Module {
  LamSpatioTemporalBlockImpl(int64_t dim, int64_t heads, double dropout);
  torch::Tensor forward(const torch::Tensor& x);  // [B, T, S, E] -> same
  LamSelfAttention spatial_attn{nullptr}, temporal_attn{nullptr};
  torch::nn::Sequential ffn{nullptr};
  LamLayerNorm norm1{nullptr}, norm2{nullptr}, norm3{nullptr};
};
TORCH_MODULE(LamSpatioTemporalBlock);

// Pre-norm block: spatial attention per frame, FFN.
struct LamSpatioBlockImpl : torch::nn::Module {
  LamSpatioBlockImpl(int64_t dim, int64_t heads, double dropout);
  torch::Tensor forward(const torch::Tensor& x);  // [B, T, S, E] -> same
  LamSelfAttention spatial_attn{nullptr};
  torch::nn::Sequential ffn{nullptr};
  LamLayerNorm norm1{nullptr}, norm2{nullptr};
};
TORCH_MODULE(LamSpatioBlock);

// ffn (LN, Linear, LN) -> + sinusoidal PE over tokens -> blocks -> out. `temporal` picks
// spatio-temporal blocks (encoder) or spatial-only blocks (decoder).
struct LamTransformerImpl : torch::nn::Module {
  LamTransformerImpl(int64_t in_dim, int64_t model_dim, int64_t out_dim, int64_t blocks, int64_t heads,
                     double dropout, bool temporal);
  torch::Tensor forward(const torch::Tensor& x);  // [B, T, S, in_dim] -> [B, T, S, out_dim]
  bool temporal;
  torch::nn::Sequential ffn{nullptr};
  torch::nn::ModuleList transformer_blocks{nullptr};
  torch::nn::Linear out{nullptr};
};
TORCH_MODULE(LamTransformer);

struct LamOutput {
  torch::Tensor z_mu;      // [B * (T - 1), latent]
  torch::Tensor z_logvar;  // [B * (T - 1), latent]
  torch::Tensor z_rep;     // [B, T - 1, 1, latent]: mu + eps * sigma in training mode, mu in eval
  torch::Tensor patches;   // [B, T, N, patch_dim]
  torch::Tensor recon;     // [B, T - 1, H, W, C] in (0, 1); only from forward()
};

struct LatentActionModelImpl : torch::nn::Module {
  explicit LatentActionModelImpl(const LamConfig& config);
  // videos: [B, T >= 2, H, W, C] float in [0, 1]. Every sample is processed on its own (no
  // sample's output depends on another's).
  LamOutput encode(const torch::Tensor& videos);
  // encode() + reconstruction of frames 1..T-1 from frames 0..T-2 and the latents.
  LamOutput forward(const torch::Tensor& videos);
  // Decoder only: frames [B, T', H, W, C] and latents [B, T', 1, latent] -> next frames.
  torch::Tensor decode(const torch::Tensor& frames, const torch::Tensor& z);

  LamConfig config;
  torch::Tensor action_prompt;  // [1, 1, 1, patch_dim]
  LamTransformer encoder{nullptr};
  torch::nn::Linear fc{nullptr}, patch_up{nullptr}, action_up{nullptr};
  LamTransformer decoder{nullptr};
};
TORCH_MODULE(LatentActionModel);

// Latent actions for clips laid out as the world model feeds them: lam_video [B, 2P, H, W, C]
// holds P frame pairs per sample ("b (p t)", t = 2). Returns [B, P, latent] (the mean, z_mu).
// Rows come back per sample: out[b, p] is the latent of sample b's pair p. published_order = true
// reproduces the released wrapper's mix-up (DreamDojo issue #23: rows made in (b p) order are read
// back as (t b)), only for comparing with the released training behaviour.
torch::Tensor lam_latent_actions(LatentActionModel& model, const torch::Tensor& lam_video,
                                 bool published_order = false);

// Matmul FLOPs (2 per multiply-add) of one forward pass over one frame pair at the config's
// input size: projections, attention scores/values, FFNs, in/out layers of both transformers.
// A training step costs about 3x this per pair (forward + backward).
double lam_forward_flops(const LamConfig& config);

struct LamLoss {
  torch::Tensor total;  // mse + beta * kl
  torch::Tensor mse;    // mean over every pixel of (target - recon)^2
  torch::Tensor kl;     // sum over latent dims, mean over samples
};
// The released loss. Scale: mse is a per-pixel mean (~1e-2) while kl is a per-sample sum over 32
// dims (nats), so at beta = 1e-6 the KL only matters once it reaches ~1e4 nats; log both.
LamLoss lam_loss(const LamOutput& out, const torch::Tensor& videos, double beta);

// --- inputs and checkpoints -----------------------------------------------------------------------

// The LAM's input range: uint8 video [...] -> float in [0, 1]; float passes through (as float32).
torch::Tensor to_unit_float(const torch::Tensor& video);

// Latent actions (z_mu) of every consecutive frame pair of one episode: frames [T, H, W, 3] uint8
// of any size (centre-cropped and resized to the model's input) -> [T - 1, latent], eval mode,
// `batch_pairs` pairs per forward pass.
torch::Tensor lam_encode_episode(LatentActionModel& model, const torch::Tensor& frames,
                                 int64_t batch_pairs = 16);

// Checkpoint directory (core/checkpoint.h): config.json holds the LamConfig, model.safetensors
// the weights as "lam.<name>" (the released Lightning checkpoint's names). No trainer state.
CheckpointData lam_checkpoint(const LatentActionModelImpl& model);
// A checkpoint written by lam_checkpoint (with or without trainer state), in eval mode. Throws
// dojo::Error naming the directory or the mismatched tensors.
LatentActionModel load_lam(const std::filesystem::path& dir);

}  // namespace dojo::models
