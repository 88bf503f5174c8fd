// Action-conditioned Cosmos-Predict2.5 DiT ("MiniTrainDIT" + action-chunk embedders), the
// DreamDojo world model. Module and parameter names equal the released checkpoint minus the
// "net." prefix, so a converted model_ema_bf16.pt loads with LoadOptions{prefix = "net."}.
// Facts: ../shared/reference/cosmos_dit.md, dreamdojo.md §5-§7, self_forcing.md §4.
//
// One network serves the bidirectional teacher and the causal student: self-attention takes an
// optional mask (block-causal over latent frames) and an optional per-block KV cache, and RoPE
// uses absolute temporal positions (DitInputs::frame_offset).
#pragma once

#include <torch/nn/module.h>
#include <torch/nn/modules/container/modulelist.h>
#include <torch/nn/modules/container/sequential.h>
#include <torch/nn/modules/linear.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

#include "models/lora.h"

namespace dojo {
class SafetensorsFile;
struct CheckpointData;
using NamedTensors = std::vector<std::pair<std::string, torch::Tensor>>;  // as core/safetensors.h
}  // namespace dojo

namespace dojo::models {

struct DitConfig {
  int64_t model_channels = 2048;  // D
  int64_t num_blocks = 28;
  int64_t num_heads = 16;  // head_dim = D / num_heads (128 released)
  int64_t adaln_lora_dim = 256;
  int64_t in_channels = 16;  // latent channels (+1 condition mask, +1 padding mask inside)
  int64_t out_channels = 16;
  int64_t patch_spatial = 2;
  int64_t patch_temporal = 1;  // only 1 is supported (the released value)
  // Text context width as fed to the net, and the width crossattn_proj maps it to. Note: the
  // Python constructor calls these crossattn_proj_in_channels and crossattn_emb_channels.
  int64_t crossattn_emb_channels = 100352;
  int64_t crossattn_proj_dim = 1024;
  bool use_crossattn_projection = true;  // false: context goes straight into cross-attn k/v
  int64_t max_img_h = 240;               // RoPE tables cover max_img / patch_spatial tokens
  int64_t max_img_w = 240;
  int64_t max_frames = 128;  // RoPE temporal length (student: 256)
  double rope_h_extrapolation_ratio = 3.0;
  double rope_w_extrapolation_ratio = 3.0;
  double rope_t_extrapolation_ratio = 1.0;
  // Initialise the RoPE exponent buffers bf16-rounded, as the released bf16 checkpoints carry
  // them (cosmos_dit.md §15). A loaded checkpoint overwrites the buffers either way.
  bool rope_bf16_ranges = true;
  double timestep_scale = 0.001;  // net time input = timesteps * timestep_scale
  int64_t action_dim = 384;
  int64_t actions_per_latent_frame = 4;
  int64_t action_hidden_dim = 0;  // 0 => 4 * D
  bool zero_init_action_fc2 = true;
  // Per action dimension, the factor the action rows are multiplied by before the action MLPs
  // (empty: 1 everywhere, the released network). Small chunk-relative deltas (min-max normalised
  // joints move ~0.02-0.3 per step) barely move fc1's output next to its bias; the release's own
  // datasets scale relative deltas by 20 in their loader for that reason. Kept in the config, so
  // every caller of a checkpoint feeds the same 384-d rows and gets the same scaling.
  std::vector<double> action_scale;
  // Ablation only (> 0): the older Cosmos action DiT's injection, one embedding of all this many
  // actions of the clip added to every latent frame, instead of 4 actions per latent frame.
  int64_t whole_clip_actions = 0;
  bool concat_padding_mask = true;
  double mlp_ratio = 4.0;
  // LoRA adapters on the blocks' attention and MLP layers (models/lora.h); rank 0: none.
  LoraConfig lora;

  static DitConfig released_2b();   // DreamDojo 2B teacher (Cosmos-Predict2.5-2B dims)
  static DitConfig released_14b();  // DreamDojo 14B teacher
  static DitConfig student_2b();    // causal student: 2B with max_frames 256
  static DitConfig golden_tiny();   // ../shared/golden/dit_tiny.md: D 64, 2 blocks, 2 heads
  static DitConfig small();         // DojoSim scale, trains on 2 CPU cores: D 256, 6 blocks, 4 heads

  int64_t head_dim() const { return model_channels / num_heads; }
  int64_t action_hidden() const { return action_hidden_dim > 0 ? action_hidden_dim : 4 * model_channels; }
  int64_t action_in_features() const {
    return (whole_clip_actions > 0 ? whole_clip_actions : actions_per_latent_frame) * action_dim;
  }
  int64_t mlp_hidden() const { return static_cast<int64_t>(model_channels * mlp_ratio); }
  int64_t crossattn_dim() const {
    return use_crossattn_projection ? crossattn_proj_dim : crossattn_emb_channels;
  }
  // Patch vector width: (latent + condition mask [+ padding mask]) * p * p * p_t.
  int64_t patch_in_features() const;
  int64_t patch_out_features() const { return patch_spatial * patch_spatial * patch_temporal * out_channels; }
  int64_t rope_seq_len() const;  // max(max_img_h / p, max_img_w / p, max_frames / p_t)

  nlohmann::json to_json() const;
  // Our own format (to_json). Missing fields keep the 2B defaults; wrong types or invalid values
  // throw dojo::Error naming the field.
  static DitConfig from_json(const nlohmann::json& j);
  // The Python constructor kwargs (as in the golden fixture's __metadata__.config), with the
  // crossattn_* naming of the reference.
  static DitConfig from_reference_kwargs(const nlohmann::json& j);
  // The architecture implied by a checkpoint's tensor shapes alone (names under `prefix`, e.g.
  // "net." for a converted release file): width from x_embedder, depth from the highest block
  // index, heads from q_norm, action width from action_embedder_B_D.fc1, RoPE length from
  // pos_embedder.seq. Assumes 16 latent channels in and out. Throws dojo::Error naming the tensor
  // when one it needs is missing or inconsistent.
  static DitConfig from_weights(const SafetensorsFile& file, const std::string& prefix = "net.");
  // The same for tensors in memory (a converted release file); `source` names them in errors.
  static DitConfig from_weights(const NamedTensors& tensors, const std::string& prefix,
                                const std::string& source);
  void validate() const;
  // The action_scale factors as a tensor [action_dim] (ones when empty).
  torch::Tensor action_scale_tensor() const;
};

// --- parameter inventory ----------------------------------------------------------------------

struct DitTensorSpec {
  std::string name;  // state-dict name without "net."
  std::vector<int64_t> shape;
  torch::Dtype dtype = torch::kFloat32;
  bool is_buffer = false;  // accum_* bookkeeping and RoPE constants
};
// Every state-dict entry of ActionDit(config), in registration order, computed from the config
// alone (no allocation): lets the 2B/14B layouts be checked without 8.6 / 59 GB of fp32.
std::vector<DitTensorSpec> dit_parameter_shapes(const DitConfig& config);
// Learned parameters (buffers excluded) implied by the config.
int64_t dit_parameter_count(const DitConfig& config);

// --- RoPE and timestep embedding --------------------------------------------------------------

// Exponents 2j/dim for j < dim/2 (float32), optionally rounded to bf16.
torch::Tensor rope_dim_range(int64_t dim, bool bf16_round);
// Head-dim split of the 3-D RoPE: h = w = head_dim / 6 * 2, t = the rest.
struct RopeAxisDims {
  int64_t t, h, w;
};
RopeAxisDims rope_axis_dims(int64_t head_dim);

// RoPE angles for a (frames, height, width) token grid in (t, h, w) order, temporal index
// starting at frame_offset: [L, 1, 1, head_dim], per token cat([t·f_t, h·f_h, w·f_w] * 2).
// The ranges are the pos_embedder buffers (rope_dim_range of the axis dims).
torch::Tensor rope_angles_3d(const torch::Tensor& dim_spatial_range, const torch::Tensor& dim_temporal_range,
                             int64_t frames, int64_t height, int64_t width, int64_t frame_offset = 0,
                             double h_ratio = 3.0, double w_ratio = 3.0, double t_ratio = 1.0);
// Same from the head dim alone (exact or bf16-rounded exponent ranges).
torch::Tensor rope_angles_3d(int64_t head_dim, int64_t frames, int64_t height, int64_t width,
                             int64_t frame_offset = 0, double h_ratio = 3.0, double w_ratio = 3.0,
                             double t_ratio = 1.0, bool bf16_ranges = false);

// Non-interleaved rotate-half rotation: x·cos + cat(-x2, x1)·sin, x [..., L, heads, d] with
// cos/sin [L, 1, d] (or anything broadcastable); computed in float32, returned in x's dtype.
torch::Tensor apply_rope(const torch::Tensor& x, const torch::Tensor& cos, const torch::Tensor& sin);
class ActionDitImpl;
// Cos and sin [head_dim] of a shift by `frames` in time (spatial angles 0) under net's RoPE: what
// DitKvCache::rotate_keys and place_sink take to move cached keys to other frame positions.
std::pair<torch::Tensor, torch::Tensor> temporal_rope_shift(const ActionDitImpl& net, int64_t frames);
// angles: [L, 1, 1, d] as from rope_angles_3d; x: [B, L, heads, d].
torch::Tensor apply_rope(const torch::Tensor& x, const torch::Tensor& angles);

// Sinusoidal embedding of already scaled times: [...] -> [..., dim], cat([cos(t·f), sin(t·f)]),
// f_i = exp(-ln(10000)·i / (dim/2)); float32.
torch::Tensor timestep_sinusoid(const torch::Tensor& t, int64_t dim);

// Keep-mask [Lq, (cached_frames + q_frames) · tokens_per_frame] for block-causal attention over
// latent frames: query frame i (absolute cached_frames + i) sees key frames j <= i, and with
// window_frames > 0 only the last window_frames of them (including its own). With sink_frames
// (< window_frames) key frames j < sink_frames stay in view of every later query in place of the
// window's oldest ones: the sink and the last window_frames - sink_frames (an attention sink).
torch::Tensor dit_block_causal_mask(int64_t q_frames, int64_t tokens_per_frame, int64_t cached_frames = 0,
                                    int64_t window_frames = 0, int64_t sink_frames = 0);

// --- modules (names as released) ---------------------------------------------------------------

// Per-block self-attention KV cache (keys after RoPE), [B, heads, L, head_dim]. Entries are
// stored detached, as the reference does. Two layouts:
//   growing (default)  cached entries are concatenated; keep_last() trims a rolling window. Works
//                      with any number of frames per call and with autograd through this call's
//                      keys (training rollouts).
//   ring (set_ring)    one preallocated buffer of window + 1 frames, one frame per call, for
//                      streaming inference: this call's frame is written into the slot of the
//                      oldest frame, every slot in use is attended (attention does not depend on
//                      key order, and RoPE is already in the keys), and commit advances the ring.
//                      No allocation after the first call; memory is flat for any horizon.
//                      An attention sink keeps the first sink_frames committed frames in their
//                      slots for good; the ring turns over the slots after them.
struct DitKvCache {
  torch::Tensor k, v;
  int64_t tokens() const;  // tokens that a call attends besides its own
  void append(const torch::Tensor& k_new, const torch::Tensor& v_new);
  // Growing layout: drop the oldest entries, keeping the sink's tokens (set_sink) and the last `tokens`.
  void keep_last(int64_t tokens);
  void clear();
  // Switches to the ring layout holding window_frames committed frames of tokens_per_frame each,
  // the first sink_frames of which (<= window_frames) are never overwritten. Empties the cache; a
  // ring of the same window and frame size keeps its buffers.
  void set_ring(int64_t window_frames, int64_t tokens_per_frame, int64_t sink_frames = 0);
  bool ring() const { return ring_tokens_ > 0; }
  int64_t committed_frames() const { return committed_; }
  // Ring: the slot the next call's frame is written to, and whether every slot is in use (from
  // then on each call attends the same number of keys).
  int64_t ring_slot() const;
  bool ring_full() const { return ring() && committed_ >= ring_frames_; }
  // Growing layout: the first `tokens` entries form an attention sink (kept by keep_last).
  void set_sink(int64_t tokens);
  // Rotates every cached key by the angles whose cos/sin are given ([head_dim], broadcast over
  // tokens): with temporal-only angles this moves the keys to other absolute frame positions.
  void rotate_keys(const torch::Tensor& cos, const torch::Tensor& sin);
  // Writes the sink's keys as first stored, rotated by cos/sin, into its slots: moves the sink in
  // time from where it was stored. From the stored copy each time, so moving it every step does
  // not pile up rounding in a bf16 cache.
  void place_sink(const torch::Tensor& cos, const torch::Tensor& sin);
  // Keys and values to attend for this call's k_new, v_new ([B, h, L, d]); with store, this
  // call's entries stay in the cache for later calls.
  std::pair<torch::Tensor, torch::Tensor> attend(const torch::Tensor& k_new, const torch::Tensor& v_new,
                                                 bool store);

 private:
  int64_t ring_frames_ = 0, ring_tokens_ = 0;  // ring: committed window, tokens per frame
  int64_t sink_frames_ = 0;                    // ring: leading frames kept for good
  int64_t sink_tokens_ = 0;                    // both layouts: leading tokens kept for good
  torch::Tensor sink_keys_;                    // the sink's keys as stored [B, h, sink_tokens, d]
  void keep_sink_keys();                       // copies them once all are stored
  int64_t committed_ = 0;                      // ring: frames committed so far
};

// x · rsqrt(mean(x²) + eps) · weight over the last dim, in float32 (TransformerEngine RMSNorm).
class DitRmsNormImpl : public torch::nn::Module {
 public:
  explicit DitRmsNormImpl(int64_t dim, double eps = 1e-6);
  torch::Tensor forward(const torch::Tensor& x);
  torch::Tensor weight;
  double eps;
};
TORCH_MODULE(DitRmsNorm);

// Self- or cross-attention with per-head q/k RMSNorm; RoPE on q, k only in self-attention.
class DitAttentionImpl : public torch::nn::Module {
 public:
  DitAttentionImpl(int64_t query_dim, int64_t context_dim, int64_t heads, int64_t head_dim,
                   const LoraConfig& lora = {});
  // Self-attention: x [B, L, D], cos/sin [L, 1, d]; mask broadcastable to [B, h, L, cached + L];
  // cache: keys/values of earlier tokens are attended first, this call's are appended when
  // store_kv. -> [B, L, D]
  torch::Tensor self_attention(const torch::Tensor& x, const torch::Tensor& cos, const torch::Tensor& sin,
                               const torch::Tensor& mask, DitKvCache* cache, bool store_kv);
  // Cross-attention: x [B, L, D], context [B, Lc, C] -> [B, L, D]
  torch::Tensor cross_attention(const torch::Tensor& x, const torch::Tensor& context);

  int64_t heads, head_dim;
  torch::nn::Linear q_proj{nullptr}, k_proj{nullptr}, v_proj{nullptr}, output_proj{nullptr};
  DitRmsNorm q_norm{nullptr}, k_norm{nullptr};
  LoraAdapter q_lora, k_lora, v_lora, output_lora;  // inactive unless the config asks for them
};
TORCH_MODULE(DitAttention);

// layer1 (D -> 4D) -> exact GELU -> layer2, no biases.
class DitMlpImpl : public torch::nn::Module {
 public:
  DitMlpImpl(int64_t dim, int64_t hidden, const LoraConfig& lora = {});
  torch::Tensor forward(const torch::Tensor& x);
  torch::nn::Linear layer1{nullptr}, layer2{nullptr};
  LoraAdapter layer1_lora, layer2_lora;
};
TORCH_MODULE(DitMlp);

// adaLN-LoRA modulation MLP: Sequential(SiLU, Linear(D, r), Linear(r, n·D)), no biases.
struct DitModulation {
  torch::nn::Sequential seq{nullptr};
  torch::nn::Linear down{nullptr}, up{nullptr};  // the same modules as seq[1], seq[2]
  DitModulation() = default;
  DitModulation(int64_t dim, int64_t lora_dim, int64_t out);
  // silu_emb: SiLU(t_emb) (shared by all modulations) [B, T, D] -> [B, T, out]
  torch::Tensor operator()(const torch::Tensor& silu_emb) const {
    return up.ptr()->forward(down.ptr()->forward(silu_emb));
  }
};

// Per-latent-frame conditioning shared by every block.
struct DitBlockContext {
  torch::Tensor silu_emb;    // SiLU(normalised t_emb) [B, T_t, D]
  torch::Tensor adaln_lora;  // [B, T_t, 3D]
  torch::Tensor cos, sin;    // RoPE [L, 1, head_dim]
  torch::Tensor context;     // projected text context [B, Lc, C]
  torch::Tensor mask;        // optional self-attention mask
  DitKvCache* cache = nullptr;
  bool store_kv = true;
};

class DitBlockImpl : public torch::nn::Module {
 public:
  explicit DitBlockImpl(const DitConfig& config);
  torch::Tensor forward(const torch::Tensor& x, const DitBlockContext& ctx);  // [B, T, S, D] -> same

  DitAttention self_attn{nullptr}, cross_attn{nullptr};
  DitMlp mlp{nullptr};
  DitModulation adaln_modulation_self_attn, adaln_modulation_cross_attn, adaln_modulation_mlp;
};
TORCH_MODULE(DitBlock);

// t_embedder.1: linear_1 (D -> D), SiLU, linear_2 (D -> 3D), no biases; returns the adaLN-LoRA.
class DitTimestepEmbeddingImpl : public torch::nn::Module {
 public:
  explicit DitTimestepEmbeddingImpl(int64_t dim);
  torch::Tensor forward(const torch::Tensor& sinusoid);  // [B, T, D] -> [B, T, 3D]
  torch::nn::Linear linear_1{nullptr}, linear_2{nullptr};
};
TORCH_MODULE(DitTimestepEmbedding);

// fc1 (+bias) -> GELU(tanh) -> fc2 (+bias).
class DitActionMlpImpl : public torch::nn::Module {
 public:
  DitActionMlpImpl(int64_t in, int64_t hidden, int64_t out);
  torch::Tensor forward(const torch::Tensor& x);
  torch::nn::Linear fc1{nullptr}, fc2{nullptr};
};
TORCH_MODULE(DitActionMlp);

// x_embedder: ModuleList(parameter-free patchify, Linear(patch_in, D, bias=false)) as "proj".
class DitPatchEmbedImpl : public torch::nn::Module {
 public:
  DitPatchEmbedImpl(int64_t in_features, int64_t dim);
  torch::nn::ModuleList proj{nullptr};
  torch::nn::Linear linear{nullptr};  // proj[1]
};
TORCH_MODULE(DitPatchEmbed);

// pos_embedder: the RoPE constant buffers (seq, dim_spatial_range, dim_temporal_range).
class DitRopeBuffersImpl : public torch::nn::Module {
 public:
  explicit DitRopeBuffersImpl(const DitConfig& config);
  torch::Tensor seq, dim_spatial_range, dim_temporal_range;
};
TORCH_MODULE(DitRopeBuffers);

// final_layer: LayerNorm (no affine), adaLN (shift, scale), linear D -> p·p·p_t·out.
class DitFinalLayerImpl : public torch::nn::Module {
 public:
  explicit DitFinalLayerImpl(const DitConfig& config);
  DitModulation adaln_modulation;
  torch::nn::Linear linear{nullptr};
};
TORCH_MODULE(DitFinalLayer);

// The action MLPs' outputs for a call's action rows (before frame 0's zero row is prepended):
// [B, T', D] added to the timestep embedding and [B, T', 3D] to the adaLN-LoRA. Constant while the
// actions are: a sampler's 35 steps of a chunk, a student's 4 hops and its re-cache pass.
struct DitActionEmbedding {
  torch::Tensor to_t_emb, to_adaln_lora;
  bool defined() const { return to_t_emb.defined(); }
};

struct DitInputs {
  torch::Tensor x;               // [B, 16, T, H, W] noisy latent (conditioning frames already replaced)
  torch::Tensor timesteps;       // [B, 1] or [B, T], network units BEFORE timestep_scale (teacher: 0..1000)
  torch::Tensor condition_mask;  // [B, 1, T, H, W]
  torch::Tensor padding_mask;    // [B, 1, H, W] or undefined => zeros
  // [B, 4·(T − 1), action_dim] when frame_offset == 0 (frame 0 gets no action term), else
  // [B, 4·T, action_dim]; undefined => zero action embedding.
  torch::Tensor actions;
  // Optional: embed_actions(actions, ...) computed once for calls that share the actions; takes
  // precedence over actions.
  DitActionEmbedding action_embedding;
  torch::Tensor context;  // [B, L, crossattn_emb_channels] or undefined => zeros [B, 1, C]
  // Optional: the context already through crossattn_proj (project_context), [B, L, proj_dim];
  // takes precedence over context. The released context is one constant per prompt, and its
  // projection costs 2·512·100352·1024 FLOPs, so callers project it once.
  torch::Tensor projected_context;
  int64_t frame_offset = 0;  // absolute temporal RoPE index of x's first latent frame (student streaming)
  // Optional: the RoPE cos and sin of this call's tokens, [L, 1, head_dim] (rope_cos_sin), used in
  // place of frame_offset's. A replayed CUDA graph reads its positions from these buffers, since
  // a position captured as a number would stay fixed.
  torch::Tensor rope_cos, rope_sin;
  // Optional self-attention mask over this call's tokens (queries) and cached + this call's tokens
  // (keys): boolean keep-mask or additive float, broadcastable to [B, heads, L, cached + L].
  torch::Tensor self_attn_mask;
  // Optional per-block KV caches (num_blocks entries): cached keys/values are attended before
  // this call's; store_kv appends this call's.
  std::vector<DitKvCache>* kv_cache = nullptr;
  bool store_kv = true;
};

class ActionDitImpl : public torch::nn::Module {
 public:
  explicit ActionDitImpl(const DitConfig& config);
  torch::Tensor forward(const DitInputs& in);  // -> velocity [B, 16, T, H, W]
  // forward() plus every intermediate under the golden fixture's names: x_embedded, rope_emb,
  // crossattn_proj_out, action_emb_B_D, action_emb_B_3D, t_emb_raw, adaln_lora_raw,
  // t_emb_normed, block{i}_out ([B, L, D]), final_layer_out, velocity.
  std::map<std::string, torch::Tensor> forward_with_intermediates(const DitInputs& in);

  // Fresh draws for fc1 of both action MLPs (post-training on a new action space).
  void reinit_action_input_layer();
  int64_t num_parameters() const;  // learned parameters (buffers excluded)
  // Projected text context crossattn_proj(context) (constant for a fixed prompt: cache it).
  torch::Tensor project_context(const torch::Tensor& context);
  // The action MLPs on `actions` [B, 4·T', action_dim] for T' latent frames with actions (the
  // config's action scaling applied): what forward() adds for them.
  DitActionEmbedding embed_actions(const torch::Tensor& actions, int64_t action_frames);
  // RoPE cos and sin [T·hp·wp, 1, head_dim] (float32) of T latent frames from frame_offset, on
  // a grid of hp x wp patches: what forward() computes for its tokens.
  std::pair<torch::Tensor, torch::Tensor> rope_cos_sin(int64_t frames, int64_t hp, int64_t wp,
                                                       int64_t frame_offset) const;

  DitConfig config;
  // Activation checkpointing (a training option, not part of the architecture): when gradients
  // are recorded and no KV cache is in use, each block keeps only its inputs in the forward pass
  // and runs again in the backward pass. Activation memory falls from every block's
  // intermediates to one block's plus the blocks' inputs, for about a third more compute.
  bool recompute_blocks = false;
  torch::Tensor accum_video_sample_counter, accum_image_sample_counter, accum_iteration, accum_train_in_hours;
  DitPatchEmbed x_embedder{nullptr};
  DitRopeBuffers pos_embedder{nullptr};
  torch::nn::ModuleList t_embedder{nullptr};
  DitTimestepEmbedding t_embedding{nullptr};  // t_embedder[1]
  torch::nn::ModuleList blocks{nullptr};
  std::vector<DitBlock> block_list;  // the same modules as blocks
  DitFinalLayer final_layer{nullptr};
  DitRmsNorm t_embedding_norm{nullptr};
  torch::nn::Sequential crossattn_proj{nullptr};
  DitActionMlp action_embedder_B_D{nullptr}, action_embedder_B_3D{nullptr};

 private:
  torch::Tensor forward_impl(const DitInputs& in, std::map<std::string, torch::Tensor>* capture);
  // config.action_scale as a tensor on the actions' device and dtype, made once per device and
  // dtype and updated in place when the config changes: a copy from host memory at every forward
  // would also break CUDA graph capture, and a graph keeps reading the address it captured. The
  // one place forward() writes module state, so a network takes one forward at a time (as the
  // server's per-model turns and the trainers give it).
  torch::Tensor action_scale_on(const torch::TensorOptions& options);
  std::vector<torch::Tensor> action_scales_;  // [action_dim] each, one per device and dtype
  std::vector<double> action_scale_of_;       // the config values they hold
};
TORCH_MODULE(ActionDit);

// Matmul FLOPs (2 per multiply-add) of one forward pass over one sample of T latent frames of
// H x W latents with a context of context_len tokens: patch embed, per block self-attention
// (projections, scores, values), cross-attention, MLP and the per-frame modulation MLPs, the
// final layer, and the timestep/action MLPs. A training step costs about 3x this per sample.
double dit_forward_flops(const DitConfig& config, int64_t T, int64_t H, int64_t W, int64_t context_len = 1);

// Frame-replace denoising (cosmos_dit.md §9): the conditioning frames of x_t are replaced by gt_x0
// before the net, and the output on them is overwritten with noise − gt_x0 (their exact velocity).
// base supplies everything but x and condition_mask. x_t, gt_x0, noise: [B, 16, T, H, W];
// condition_mask [B, 1, T, H, W].
torch::Tensor denoise_velocity(ActionDitImpl& net, const DitInputs& base, const torch::Tensor& x_t,
                               const torch::Tensor& gt_x0, const torch::Tensor& noise,
                               const torch::Tensor& condition_mask);

// --- checkpoints ---------------------------------------------------------------------------------

// Checkpoint directory (core/checkpoint.h): config.json holds {"model": "action_dit", "config":
// DitConfig}, model.safetensors the weights as "net.<name>" (the released names), CPU float32; a
// network with LoRA adapters keeps them in adapter_model.safetensors ("net.<layer>.lora_A.default.
// weight", ...), the base weights staying in model.safetensors.
CheckpointData world_model_checkpoint(const ActionDitImpl& net);
// A world-model checkpoint (with or without trainer state) -> the network in eval mode on `device`.
// Trainers store their EMA weights as the model, so this is the EMA network. LoRA adapters beside
// the base weights are folded in (W + alpha/r · B A): the network returned has none.
ActionDit load_world_model(const std::filesystem::path& dir, torch::Device device = torch::kCPU);

}  // namespace dojo::models
