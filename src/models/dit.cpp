#include "models/dit.h"

#include <torch/autograd.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/autocast.h"
#include "core/error.h"
#include "models/attention.h"
#include "models/dit_kernels.h"

namespace dojo::models {

namespace nn = torch::nn;

// ---------------------------------------------------------------------------------------------
// RoPE, timestep embedding, masks

torch::Tensor rope_dim_range(int64_t dim, bool bf16_round) {
  // As the reference: arange(0, dim, 2)[:dim // 2].float() / dim.
  auto range = torch::arange(0, dim, 2, torch::kLong).slice(0, 0, dim / 2).to(torch::kFloat32) / dim;
  if (bf16_round) range = range.to(torch::kBFloat16).to(torch::kFloat32);
  return range;
}

RopeAxisDims rope_axis_dims(int64_t head_dim) {
  const int64_t hw = head_dim / 6 * 2;
  return {head_dim - 2 * hw, hw, hw};
}

namespace {
// 1 / (10000 · ratio^(dim / (dim − 2)))^range, float32 ops in the reference's order.
torch::Tensor rope_freqs(const torch::Tensor& range, double ratio) {
  const double dim = static_cast<double>(range.size(0) * 2);
  const double theta = 10000.0 * std::pow(ratio, dim / (dim - 2.0));
  return torch::reciprocal(torch::pow(theta, range.to(torch::kFloat32)));
}
}  // namespace

torch::Tensor rope_angles_3d(const torch::Tensor& dim_spatial_range, const torch::Tensor& dim_temporal_range,
                             int64_t frames, int64_t height, int64_t width, int64_t frame_offset,
                             double h_ratio, double w_ratio, double t_ratio) {
  const auto freqs_h = rope_freqs(dim_spatial_range, h_ratio);   // [dh / 2]
  const auto freqs_w = rope_freqs(dim_spatial_range, w_ratio);   // [dw / 2]
  const auto freqs_t = rope_freqs(dim_temporal_range, t_ratio);  // [dt / 2]
  const auto opts = freqs_h.options();
  const auto pos_t = torch::arange(frame_offset, frame_offset + frames, opts);
  const auto half_t = torch::outer(pos_t, freqs_t);                        // [T, dt / 2]
  const auto half_h = torch::outer(torch::arange(height, opts), freqs_h);  // [H, dh / 2]
  const auto half_w = torch::outer(torch::arange(width, opts), freqs_w);   // [W, dw / 2]
  const int64_t nt = half_t.size(1), nh = half_h.size(1), nw = half_w.size(1);
  const auto t = half_t.view({frames, 1, 1, nt}).expand({frames, height, width, nt});
  const auto h = half_h.view({1, height, 1, nh}).expand({frames, height, width, nh});
  const auto w = half_w.view({1, 1, width, nw}).expand({frames, height, width, nw});
  const auto angles = torch::cat({t, h, w, t, h, w}, -1);  // [T, H, W, d]
  return angles.reshape({frames * height * width, 1, 1, 2 * (nt + nh + nw)});
}

torch::Tensor rope_angles_3d(int64_t head_dim, int64_t frames, int64_t height, int64_t width,
                             int64_t frame_offset, double h_ratio, double w_ratio, double t_ratio,
                             bool bf16_ranges) {
  const auto axes = rope_axis_dims(head_dim);
  return rope_angles_3d(rope_dim_range(axes.h, bf16_ranges), rope_dim_range(axes.t, bf16_ranges), frames,
                        height, width, frame_offset, h_ratio, w_ratio, t_ratio);
}

torch::Tensor apply_rope(const torch::Tensor& x, const torch::Tensor& cos, const torch::Tensor& sin) {
  const auto xf = x.to(torch::kFloat32);
  const int64_t half = x.size(-1) / 2;
  const auto rotated = torch::cat({-xf.slice(-1, half), xf.slice(-1, 0, half)}, -1);  // rotate_half
  return (xf * cos + rotated * sin).to(x.scalar_type());
}

torch::Tensor apply_rope(const torch::Tensor& x, const torch::Tensor& angles) {
  const auto a = angles.to(torch::kFloat32).flatten(1, 2);  // [L, 1, d]
  return apply_rope(x, a.cos(), a.sin());
}

torch::Tensor timestep_sinusoid(const torch::Tensor& t, int64_t dim) {
  const int64_t half = dim / 2;
  auto exponent = -std::log(10000.0) *
                  torch::arange(half, torch::TensorOptions().dtype(torch::kFloat32).device(t.device()));
  exponent = exponent / static_cast<double>(half);
  const auto freqs = torch::exp(exponent);                        // [half]
  const auto args = t.to(torch::kFloat32).unsqueeze(-1) * freqs;  // [..., half]
  return torch::cat({torch::cos(args), torch::sin(args)}, -1);    // [..., dim]
}

torch::Tensor dit_block_causal_mask(int64_t q_frames, int64_t tokens_per_frame, int64_t cached_frames,
                                    int64_t window_frames, int64_t sink_frames) {
  const auto q_frame =
      (torch::arange(q_frames, torch::kLong) + cached_frames).repeat_interleave(tokens_per_frame);
  const auto k_frame =
      torch::arange(cached_frames + q_frames, torch::kLong).repeat_interleave(tokens_per_frame);
  auto keep = k_frame.unsqueeze(0).le(q_frame.unsqueeze(1));  // [Lq, Lk]
  DOJO_CHECK(sink_frames == 0 || sink_frames < window_frames,
             "dit_block_causal_mask: a sink of " + std::to_string(sink_frames) +
                 " frames must be smaller than the window (" + std::to_string(window_frames) + ")");
  if (window_frames > 0) {
    // A sink takes the oldest places of the window: the last window - sink frames, then the sink.
    auto in_view = k_frame.unsqueeze(0).gt(q_frame.unsqueeze(1) - (window_frames - sink_frames));
    if (sink_frames > 0) in_view = in_view.logical_or(k_frame.lt(sink_frames).unsqueeze(0));
    keep = keep.logical_and(in_view);
  }
  return keep;
}

// ---------------------------------------------------------------------------------------------
// Modules

int64_t DitKvCache::tokens() const {
  if (!k.defined()) return 0;
  return ring() ? std::min(committed_, ring_frames_) * ring_tokens_ : k.size(2);
}

void DitKvCache::append(const torch::Tensor& k_new, const torch::Tensor& v_new) {
  DOJO_CHECK(!ring(), "DitKvCache: append() is for the growing layout");
  if (!k.defined()) {
    k = k_new.detach();
    v = v_new.detach();
  } else {
    k = torch::cat({k, k_new.detach()}, 2);
    v = torch::cat({v, v_new.detach()}, 2);
  }
  keep_sink_keys();
}

void DitKvCache::keep_sink_keys() {
  if (sink_tokens_ > 0 && !sink_keys_.defined() && tokens() >= sink_tokens_)
    sink_keys_ = k.narrow(2, 0, sink_tokens_).clone();  // [B, h, sink_tokens, d]
}

void DitKvCache::set_sink(int64_t tokens_in_sink) {
  DOJO_CHECK(!ring() && tokens_in_sink >= 0, "DitKvCache: set_sink() is for the growing layout");
  sink_tokens_ = tokens_in_sink;
  sink_keys_ = torch::Tensor();
  keep_sink_keys();
}

void DitKvCache::keep_last(int64_t tokens_to_keep) {
  DOJO_CHECK(!ring(), "DitKvCache: keep_last() is for the growing layout (a ring keeps its window)");
  const int64_t lead = std::min(sink_tokens_, tokens());
  if (tokens() <= lead + tokens_to_keep) return;
  if (lead + tokens_to_keep <= 0) return clear();
  const auto kept = [&](const torch::Tensor& x) {  // [B, h, L, d] -> [B, h, lead + kept, d]
    return torch::cat({x.narrow(2, 0, lead), x.narrow(2, x.size(2) - tokens_to_keep, tokens_to_keep)}, 2);
  };
  k = kept(k);
  v = kept(v);
}

void DitKvCache::clear() {
  committed_ = 0;
  sink_keys_ = torch::Tensor();
  if (!ring()) k = v = torch::Tensor();  // a ring keeps its buffer: reset is allocation-free
}

void DitKvCache::rotate_keys(const torch::Tensor& cos, const torch::Tensor& sin) {
  if (!k.defined()) return;
  torch::NoGradGuard no_grad;
  k.copy_(apply_rope(k, cos, sin));  // [B, h, L, d]; in place keeps a ring's buffer
}

void DitKvCache::place_sink(const torch::Tensor& cos, const torch::Tensor& sin) {
  DOJO_CHECK(sink_keys_.defined(), "DitKvCache: place_sink() before the sink's frames were stored");
  torch::NoGradGuard no_grad;
  k.narrow(2, 0, sink_tokens_).copy_(apply_rope(sink_keys_, cos, sin));
}

void DitKvCache::set_ring(int64_t window_frames, int64_t tokens_per_frame, int64_t sink_frames) {
  DOJO_CHECK(window_frames >= 0 && tokens_per_frame > 0 && sink_frames >= 0 && sink_frames <= window_frames,
             "DitKvCache: ring needs a window >= 0, tokens > 0 and 0 <= sink <= window");
  // The same layout keeps its buffers (a new stream writes over them as it fills): no allocation,
  // and their addresses stay those that captured CUDA graphs of the streaming engine hold.
  if (!ring() || window_frames != ring_frames_ || tokens_per_frame != ring_tokens_) k = v = torch::Tensor();
  ring_frames_ = window_frames;
  ring_tokens_ = tokens_per_frame;
  sink_frames_ = sink_frames;
  sink_tokens_ = sink_frames * tokens_per_frame;
  sink_keys_ = torch::Tensor();
  committed_ = 0;
}

int64_t DitKvCache::ring_slot() const {
  // The slot after the newest committed frame: empty while filling, then the oldest one after the
  // sink, which falls out of the window now.
  const int64_t slots = ring_frames_ + 1;
  return committed_ < sink_frames_ ? committed_
                                   : sink_frames_ + (committed_ - sink_frames_) % (slots - sink_frames_);
}

std::pair<torch::Tensor, torch::Tensor> DitKvCache::attend(const torch::Tensor& k_new,
                                                           const torch::Tensor& v_new, bool store) {
  if (!ring()) {
    std::pair<torch::Tensor, torch::Tensor> all{k_new, v_new};
    if (tokens() > 0) all = {torch::cat({k, k_new}, 2), torch::cat({v, v_new}, 2)};  // [B, h, cached + L, d]
    if (store) append(k_new, v_new);
    return all;
  }
  DOJO_CHECK(k_new.size(2) == ring_tokens_, "DitKvCache: a ring takes one frame of " +
                                                std::to_string(ring_tokens_) + " tokens per call, got " +
                                                std::to_string(k_new.size(2)));
  const int64_t slots = ring_frames_ + 1;  // the window plus this call's frame
  if (!k.defined() || k.size(0) != k_new.size(0) || k.scalar_type() != k_new.scalar_type()) {
    auto shape = k_new.sizes().vec();
    shape[2] = slots * ring_tokens_;
    k = torch::empty(shape, k_new.options());  // [B, h, slots · S, d]
    v = torch::empty(shape, v_new.options());
    committed_ = 0;  // a new batch or dtype: nothing cached is valid
    sink_keys_ = torch::Tensor();
  }
  const int64_t slot = ring_slot();
  DOJO_CHECK(!(torch::GradMode::is_enabled() && k_new.requires_grad()),
             "DitKvCache: the ring layout is for inference; train through the growing layout");
  torch::NoGradGuard no_grad;  // entries are stored detached, as in the growing layout
  k.narrow(2, slot * ring_tokens_, ring_tokens_).copy_(k_new);
  v.narrow(2, slot * ring_tokens_, ring_tokens_).copy_(v_new);
  const int64_t used = std::min(committed_ + 1, slots) * ring_tokens_;
  if (store) {
    ++committed_;
    if (committed_ == sink_frames_) keep_sink_keys();
  }
  return {k.narrow(2, 0, used), v.narrow(2, 0, used)};
}

std::pair<torch::Tensor, torch::Tensor> temporal_rope_shift(const ActionDitImpl& net, int64_t frames) {
  const auto& c = net.config;
  const auto angles =
      rope_angles_3d(net.pos_embedder->dim_spatial_range, net.pos_embedder->dim_temporal_range, 1, 1, 1,
                     frames, c.rope_h_extrapolation_ratio, c.rope_w_extrapolation_ratio,
                     c.rope_t_extrapolation_ratio)
          .flatten();  // [head_dim]: temporal angles of `frames`, spatial 0
  return {angles.cos(), angles.sin()};
}

DitRmsNormImpl::DitRmsNormImpl(int64_t dim, double eps_) : eps(eps_) {
  weight = register_parameter("weight", torch::ones({dim}));
}

torch::Tensor DitRmsNormImpl::forward(const torch::Tensor& x) {
  const auto xf = x.to(torch::kFloat32);
  return (xf * torch::rsqrt(xf.pow(2).mean(-1, /*keepdim=*/true) + eps) * weight.to(torch::kFloat32))
      .to(x.scalar_type());
}

DitAttentionImpl::DitAttentionImpl(int64_t query_dim, int64_t context_dim, int64_t heads_, int64_t head_dim_,
                                   const LoraConfig& lora)
    : heads(heads_), head_dim(head_dim_) {
  const int64_t inner = heads * head_dim;
  q_proj = register_module("q_proj", nn::Linear(nn::LinearOptions(query_dim, inner).bias(false)));
  q_norm = register_module("q_norm", DitRmsNorm(head_dim));
  k_proj = register_module("k_proj", nn::Linear(nn::LinearOptions(context_dim, inner).bias(false)));
  k_norm = register_module("k_norm", DitRmsNorm(head_dim));
  v_proj = register_module("v_proj", nn::Linear(nn::LinearOptions(context_dim, inner).bias(false)));
  output_proj = register_module("output_proj", nn::Linear(nn::LinearOptions(inner, query_dim).bias(false)));
  q_lora = attach_lora(q_proj, "q", lora);
  k_lora = attach_lora(k_proj, "k", lora);
  v_lora = attach_lora(v_proj, "v", lora);
  output_lora = attach_lora(output_proj, "o", lora);
}

torch::Tensor DitAttentionImpl::self_attention(const torch::Tensor& x, const torch::Tensor& cos,
                                               const torch::Tensor& sin, const torch::Tensor& mask,
                                               DitKvCache* cache, bool store_kv) {
  const int64_t B = x.size(0), L = x.size(1);
  // Norm and RoPE act per head on the [B, L, h, d] layout the projections produce; the
  // transposes to [B, h, L, d] are views (the attention matmuls take them as they are).
  const auto q_raw = lora_forward(q_proj, q_lora, x).view({B, L, heads, head_dim});
  const auto k_raw = lora_forward(k_proj, k_lora, x).view({B, L, heads, head_dim});
  torch::Tensor q, k;           // [B, h, L, d]
  std::optional<double> scale;  // attention's default 1/sqrt(d), unless folded into q
  if (fused_dit_kernels_apply({q_raw})) {
    q = rms_norm_rope_fused(q_raw, q_norm->weight, q_norm->eps, cos, sin,
                            1.0 / std::sqrt(static_cast<double>(head_dim)))
            .transpose(1, 2);
    k = rms_norm_rope_fused(k_raw, k_norm->weight, k_norm->eps, cos, sin).transpose(1, 2);
    scale = 1.0;
  } else {
    q = apply_rope(q_norm(q_raw), cos, sin).transpose(1, 2);
    k = apply_rope(k_norm(k_raw), cos, sin).transpose(1, 2);
  }
  auto v = lora_forward(v_proj, v_lora, x).view({B, L, heads, head_dim}).transpose(1, 2);  // [B, h, L, d]
  torch::Tensor k_all = k, v_all = v;  // [B, h, cached + L, d]
  if (cache != nullptr) std::tie(k_all, v_all) = cache->attend(k, v, store_kv);
  std::optional<torch::Tensor> m;
  if (mask.defined()) m = mask;
  const auto o = attention(q, k_all, v_all, m, /*causal=*/false, scale);  // [B, h, L, d]
  return lora_forward(output_proj, output_lora,
                      o.transpose(1, 2).reshape({B, L, heads * head_dim}));  // [B, L, D]
}

torch::Tensor DitAttentionImpl::cross_attention(const torch::Tensor& x, const torch::Tensor& context) {
  const int64_t B = x.size(0), L = x.size(1), Lc = context.size(1);
  const auto q_raw = lora_forward(q_proj, q_lora, x).view({B, L, heads, head_dim});
  const auto k_raw = lora_forward(k_proj, k_lora, context).view({B, Lc, heads, head_dim});
  const auto v = lora_forward(v_proj, v_lora, context).view({B, Lc, heads, head_dim}).transpose(1, 2);
  if (fused_dit_kernels_apply({q_raw})) {
    const auto q = rms_norm_rope_fused(q_raw, q_norm->weight, q_norm->eps, {}, {},
                                       1.0 / std::sqrt(static_cast<double>(head_dim)));
    const auto k = rms_norm_rope_fused(k_raw, k_norm->weight, k_norm->eps, {}, {});
    const auto o =
        attention(q.transpose(1, 2), k.transpose(1, 2), v, std::nullopt, false, 1.0);  // [B, h, L, d]
    return lora_forward(output_proj, output_lora, o.transpose(1, 2).reshape({B, L, heads * head_dim}));
  }
  const auto q = q_norm(q_raw).transpose(1, 2);
  const auto k = k_norm(k_raw).transpose(1, 2);
  const auto o = attention(q, k, v);  // [B, h, L, d]
  return lora_forward(output_proj, output_lora,
                      o.transpose(1, 2).reshape({B, L, heads * head_dim}));  // [B, L, D]
}

DitMlpImpl::DitMlpImpl(int64_t dim, int64_t hidden, const LoraConfig& lora) {
  layer1 = register_module("layer1", nn::Linear(nn::LinearOptions(dim, hidden).bias(false)));
  layer2 = register_module("layer2", nn::Linear(nn::LinearOptions(hidden, dim).bias(false)));
  layer1_lora = attach_lora(layer1, "mlp1", lora);
  layer2_lora = attach_lora(layer2, "mlp2", lora);
}

torch::Tensor DitMlpImpl::forward(const torch::Tensor& x) {
  return lora_forward(layer2, layer2_lora, torch::gelu(lora_forward(layer1, layer1_lora, x)));
}

DitModulation::DitModulation(int64_t dim, int64_t lora_dim, int64_t out)
    : down(nn::LinearOptions(dim, lora_dim).bias(false)), up(nn::LinearOptions(lora_dim, out).bias(false)) {
  seq = nn::Sequential(nn::SiLU(), down, up);
}

namespace {
// LayerNorm without affine parameters (eps 1e-6), then adaLN: norm · (1 + scale) + shift.
torch::Tensor modulate(const torch::Tensor& x, const torch::Tensor& shift, const torch::Tensor& scale) {
  // Under bf16 autocast the shift and scale come out of the modulation MLP in bf16: plain path.
  return fused_dit_kernels_apply({x, shift, scale}) ? modulate_fused(x, shift, scale)
                                                    : modulate_plain(x, shift, scale);
}

// The residual branch r added back under its gate: x + gate · r.
torch::Tensor gated_residual(const torch::Tensor& x, const torch::Tensor& gate, const torch::Tensor& r) {
  return fused_dit_kernels_apply({x, gate, r}) ? gated_residual_fused(x, gate, r)
                                               : gated_residual_plain(x, gate, r);
}
}  // namespace

DitBlockImpl::DitBlockImpl(const DitConfig& c) {
  const int64_t D = c.model_channels;
  self_attn = register_module("self_attn", DitAttention(D, D, c.num_heads, c.head_dim(), c.lora));
  cross_attn =
      register_module("cross_attn", DitAttention(D, c.crossattn_dim(), c.num_heads, c.head_dim(), c.lora));
  mlp = register_module("mlp", DitMlp(D, c.mlp_hidden(), c.lora));
  adaln_modulation_self_attn = DitModulation(D, c.adaln_lora_dim, 3 * D);
  adaln_modulation_cross_attn = DitModulation(D, c.adaln_lora_dim, 3 * D);
  adaln_modulation_mlp = DitModulation(D, c.adaln_lora_dim, 3 * D);
  register_module("adaln_modulation_self_attn", adaln_modulation_self_attn.seq);
  register_module("adaln_modulation_cross_attn", adaln_modulation_cross_attn.seq);
  register_module("adaln_modulation_mlp", adaln_modulation_mlp.seq);
}

torch::Tensor DitBlockImpl::forward(const torch::Tensor& input, const DitBlockContext& ctx) {
  const int64_t B = input.size(0), T = input.size(1), S = input.size(2), D = input.size(3);
  // (shift, scale, gate) per latent frame, broadcast over the frame's tokens: [B, T_t, 1, D] each.
  auto mod = [&](const DitModulation& m) {
    return (m(ctx.silu_emb) + ctx.adaln_lora).unsqueeze(2).chunk(3, -1);
  };
  const auto sa = mod(adaln_modulation_self_attn);
  const auto ca = mod(adaln_modulation_cross_attn);
  const auto ml = mod(adaln_modulation_mlp);

  auto x = input;  // [B, T, S, D]
  auto y = modulate(x, sa[0], sa[1]).view({B, T * S, D});
  auto r = self_attn->self_attention(y, ctx.cos, ctx.sin, ctx.mask, ctx.cache, ctx.store_kv);
  x = gated_residual(x, sa[2], r.view({B, T, S, D}));

  y = modulate(x, ca[0], ca[1]).view({B, T * S, D});
  r = cross_attn->cross_attention(y, ctx.context);
  x = gated_residual(x, ca[2], r.view({B, T, S, D}));

  y = modulate(x, ml[0], ml[1]);
  return gated_residual(x, ml[2], mlp(y));
}

namespace {

// One block under activation checkpointing: the forward pass runs it without recording (only the
// inputs are kept); the backward pass runs it again with gradients recorded and backpropagates
// through that, which also accumulates the block's parameter gradients (the re-entrant scheme of
// torch.utils.checkpoint). The block has no randomness, so both passes compute the same function.
struct RecomputedBlock : torch::autograd::Function<RecomputedBlock> {
  // libtorch 1.13 refuses undefined tensors among a Function's inputs: an empty one stands for
  // "no mask".
  static torch::Tensor no_mask() { return torch::empty({0}, torch::kBool); }
  static torch::Tensor mask_of(const torch::Tensor& t) { return t.numel() == 0 ? torch::Tensor() : t; }

  static torch::Tensor forward(torch::autograd::AutogradContext* ctx, const torch::Tensor& x,
                               const torch::Tensor& silu_emb, const torch::Tensor& adaln_lora,
                               const torch::Tensor& context, const torch::Tensor& cos,
                               const torch::Tensor& sin, const torch::Tensor& mask, int64_t block) {
    ctx->save_for_backward({x, silu_emb, adaln_lora, context, cos, sin, mask});
    ctx->saved_data["block"] = block;
    // The backward pass runs outside the training step's autocast region: the recompute takes the
    // forward's autocast state with it, or a bf16 forward is recomputed in float32 (1.2 % off).
    const auto device = x.device().type();
    ctx->saved_data["autocast"] = AutocastGuard::is_enabled(device);
    ctx->saved_data["autocast_dtype"] = static_cast<int64_t>(AutocastGuard::dtype(device));
    // No gradients here, gradients in the recompute: the fused kernels' two paths share their
    // arithmetic, so in float32 both runs compute the same values bit for bit; under autocast the
    // recompute takes the plain path (dit_kernels.h), and so does this run.
    std::optional<PlainDitKernelsScope> plain;
    if (AutocastGuard::is_enabled(device)) plain.emplace();
    DitBlockContext c;
    c.silu_emb = silu_emb;
    c.adaln_lora = adaln_lora;
    c.context = context;
    c.cos = cos;
    c.sin = sin;
    c.mask = mask_of(mask);
    return reinterpret_cast<DitBlockImpl*>(block)->forward(x, c);
  }

  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 torch::autograd::variable_list grad_out) {
    const auto saved = ctx->get_saved_variables();
    std::vector<torch::Tensor> inputs;  // x, silu_emb, adaln_lora, context, detached
    for (int i = 0; i < 4; ++i)
      inputs.push_back(saved[i].defined() ? saved[i].detach().requires_grad_(ctx->needs_input_grad(i))
                                          : saved[i]);
    torch::Tensor out;
    {
      torch::AutoGradMode recording(true);
      const bool autocast = ctx->saved_data["autocast"].toBool();
      AutocastGuard as_in_forward(
          inputs[0].device().type(),
          autocast ? static_cast<c10::ScalarType>(ctx->saved_data["autocast_dtype"].toInt()) : c10::kBFloat16,
          autocast);
      // The block sees views of the detached inputs, not the leaves themselves: autocast caches its
      // lower-precision copy of a leaf that needs a gradient and reuses it for every use, so the
      // gradients of silu_emb's three modulations would be summed in bf16 before the cast back
      // (3e-4 off the forward's, where each use had its own cast).
      const auto as_in_forward_graph = [](const torch::Tensor& t) { return t.defined() ? t.view_as(t) : t; };
      DitBlockContext c;
      c.silu_emb = as_in_forward_graph(inputs[1]);
      c.adaln_lora = as_in_forward_graph(inputs[2]);
      c.context = as_in_forward_graph(inputs[3]);
      c.cos = saved[4];
      c.sin = saved[5];
      c.mask = mask_of(saved[6]);
      out = reinterpret_cast<DitBlockImpl*>(ctx->saved_data["block"].toInt())
                ->forward(as_in_forward_graph(inputs[0]), c);
    }
    torch::autograd::backward({out}, {grad_out[0]});
    torch::autograd::variable_list grads;
    for (const auto& t : inputs)
      grads.push_back(t.defined() && t.requires_grad() ? t.grad() : torch::Tensor());
    grads.resize(8);  // cos, sin, mask and the block take none
    return grads;
  }
};

}  // namespace

DitTimestepEmbeddingImpl::DitTimestepEmbeddingImpl(int64_t dim) {
  linear_1 = register_module("linear_1", nn::Linear(nn::LinearOptions(dim, dim).bias(false)));
  linear_2 = register_module("linear_2", nn::Linear(nn::LinearOptions(dim, 3 * dim).bias(false)));
}

torch::Tensor DitTimestepEmbeddingImpl::forward(const torch::Tensor& sinusoid) {
  return linear_2(torch::silu(linear_1(sinusoid)));
}

DitActionMlpImpl::DitActionMlpImpl(int64_t in, int64_t hidden, int64_t out) {
  fc1 = register_module("fc1", nn::Linear(in, hidden));
  fc2 = register_module("fc2", nn::Linear(hidden, out));
}

torch::Tensor DitActionMlpImpl::forward(const torch::Tensor& x) { return fc2(torch::gelu(fc1(x), "tanh")); }

DitPatchEmbedImpl::DitPatchEmbedImpl(int64_t in_features, int64_t dim) {
  linear = nn::Linear(nn::LinearOptions(in_features, dim).bias(false));
  proj = register_module("proj", nn::ModuleList(nn::Identity(), linear));
}

DitRopeBuffersImpl::DitRopeBuffersImpl(const DitConfig& c) {
  const auto axes = rope_axis_dims(c.head_dim());
  seq = register_buffer("seq", torch::arange(c.rope_seq_len(), torch::kFloat32));
  dim_spatial_range = register_buffer("dim_spatial_range", rope_dim_range(axes.h, c.rope_bf16_ranges));
  dim_temporal_range = register_buffer("dim_temporal_range", rope_dim_range(axes.t, c.rope_bf16_ranges));
}

DitFinalLayerImpl::DitFinalLayerImpl(const DitConfig& c) {
  const int64_t D = c.model_channels;
  linear = register_module("linear", nn::Linear(nn::LinearOptions(D, c.patch_out_features()).bias(false)));
  adaln_modulation = DitModulation(D, c.adaln_lora_dim, 2 * D);
  register_module("adaln_modulation", adaln_modulation.seq);
}

ActionDitImpl::ActionDitImpl(const DitConfig& c) : config(c) {
  config.validate();
  const int64_t D = c.model_channels;
  accum_video_sample_counter = register_buffer("accum_video_sample_counter", torch::zeros({}, torch::kInt64));
  accum_image_sample_counter = register_buffer("accum_image_sample_counter", torch::zeros({}, torch::kInt64));
  accum_iteration = register_buffer("accum_iteration", torch::zeros({}, torch::kInt64));
  accum_train_in_hours = register_buffer("accum_train_in_hours", torch::zeros({}, torch::kFloat32));
  x_embedder = register_module("x_embedder", DitPatchEmbed(c.patch_in_features(), D));
  pos_embedder = register_module("pos_embedder", DitRopeBuffers(c));
  t_embedding = DitTimestepEmbedding(D);
  t_embedder = register_module("t_embedder", nn::ModuleList(nn::Identity(), t_embedding));
  blocks = register_module("blocks", nn::ModuleList());
  for (int64_t i = 0; i < c.num_blocks; ++i) {
    block_list.push_back(DitBlock(c));
    blocks->push_back(block_list.back());
  }
  final_layer = register_module("final_layer", DitFinalLayer(c));
  t_embedding_norm = register_module("t_embedding_norm", DitRmsNorm(D));
  if (c.use_crossattn_projection)
    crossattn_proj = register_module(
        "crossattn_proj",
        nn::Sequential(nn::Linear(c.crossattn_emb_channels, c.crossattn_proj_dim), nn::GELU()));
  action_embedder_B_D =
      register_module("action_embedder_B_D", DitActionMlp(c.action_in_features(), c.action_hidden(), D));
  action_embedder_B_3D =
      register_module("action_embedder_B_3D", DitActionMlp(c.action_in_features(), c.action_hidden(), 3 * D));
  if (c.zero_init_action_fc2) {
    torch::NoGradGuard no_grad;
    for (auto* mlp : {action_embedder_B_D.get(), action_embedder_B_3D.get()}) {
      mlp->fc2->weight.zero_();
      mlp->fc2->bias.zero_();
    }
  }
}

void ActionDitImpl::reinit_action_input_layer() {
  action_embedder_B_D->fc1->reset_parameters();
  action_embedder_B_3D->fc1->reset_parameters();
}

int64_t ActionDitImpl::num_parameters() const {
  int64_t n = 0;
  for (const auto& p : parameters()) n += p.numel();
  return n;
}

torch::Tensor ActionDitImpl::project_context(const torch::Tensor& context) {
  DOJO_CHECK(context.dim() == 3 && context.size(2) == config.crossattn_emb_channels,
             "DiT: context must be [B, L, " + std::to_string(config.crossattn_emb_channels) + "]");
  const auto ctx = context.to(x_embedder->linear->weight.scalar_type());
  return config.use_crossattn_projection ? crossattn_proj->forward(ctx) : ctx;  // [B, L, C]
}

std::pair<torch::Tensor, torch::Tensor> ActionDitImpl::rope_cos_sin(int64_t frames, int64_t hp, int64_t wp,
                                                                    int64_t frame_offset) const {
  const auto& c = config;
  const auto angles = rope_angles_3d(pos_embedder->dim_spatial_range, pos_embedder->dim_temporal_range,
                                     frames, hp, wp, frame_offset, c.rope_h_extrapolation_ratio,
                                     c.rope_w_extrapolation_ratio, c.rope_t_extrapolation_ratio)
                          .flatten(1, 2);  // [L, 1, d]
  return {angles.cos(), angles.sin()};
}

torch::Tensor ActionDitImpl::forward(const DitInputs& in) { return forward_impl(in, nullptr); }

torch::Tensor ActionDitImpl::action_scale_on(const torch::TensorOptions& options) {
  c10::InferenceMode normal_tensors(false);  // usable by training after an inference-mode forward
  torch::NoGradGuard no_grad;
  if (action_scale_of_ != config.action_scale) {
    const auto values = config.action_scale_tensor();  // [action_dim]
    for (auto& t : action_scales_) t.copy_(values);    // in place: captured addresses stay valid
    action_scale_of_ = config.action_scale;
  }
  for (const auto& t : action_scales_)
    if (t.device() == options.device() && t.dtype() == options.dtype()) return t;
  action_scales_.push_back(config.action_scale_tensor().to(options));
  return action_scales_.back();
}

DitActionEmbedding ActionDitImpl::embed_actions(const torch::Tensor& actions_in, int64_t action_frames) {
  const auto& c = config;
  const int64_t k = c.actions_per_latent_frame;
  DOJO_CHECK(c.whole_clip_actions == 0, "DiT: embed_actions is for per-frame action injection");
  DOJO_CHECK(
      actions_in.dim() == 3 && actions_in.size(1) == k * action_frames && actions_in.size(2) == c.action_dim,
      "DiT: actions must be [B, " + std::to_string(k * action_frames) + ", " + std::to_string(c.action_dim) +
          "] for " + std::to_string(action_frames) + " latent frames with actions");
  const auto actions =
      c.action_scale.empty() ? actions_in : actions_in * action_scale_on(actions_in.options());
  const auto rows = actions.to(x_embedder->linear->weight.scalar_type())
                        .reshape({actions.size(0), action_frames, k * c.action_dim});  // [B, T', 4A]
  return {action_embedder_B_D(rows), action_embedder_B_3D(rows)};  // [B, T', D], [B, T', 3D]
}

std::map<std::string, torch::Tensor> ActionDitImpl::forward_with_intermediates(const DitInputs& in) {
  std::map<std::string, torch::Tensor> out;
  out["velocity"] = forward_impl(in, &out);
  return out;
}

torch::Tensor ActionDitImpl::forward_impl(const DitInputs& in,
                                          std::map<std::string, torch::Tensor>* capture) {
  const auto& c = config;
  DOJO_CHECK(in.x.defined() && in.x.dim() == 5 && in.x.size(1) == c.in_channels,
             "DiT: x must be [B, " + std::to_string(c.in_channels) + ", T, H, W]");
  const int64_t B = in.x.size(0), T = in.x.size(2), H = in.x.size(3), W = in.x.size(4);
  const int64_t p = c.patch_spatial, D = c.model_channels;
  DOJO_CHECK(H % p == 0 && W % p == 0, "DiT: latent H and W must be multiples of patch_spatial");
  const int64_t Hp = H / p, Wp = W / p, S = Hp * Wp, L = T * S;
  DOJO_CHECK(Hp <= c.max_img_h / p && Wp <= c.max_img_w / p,
             "DiT: latent " + std::to_string(H) + "x" + std::to_string(W) + " exceeds max_img_h/max_img_w");
  DOJO_CHECK(in.frame_offset >= 0 && in.frame_offset + T <= pos_embedder->seq.size(0),
             "DiT: frames [frame_offset, frame_offset + T) exceed the RoPE length (max_frames)");
  const auto dtype = x_embedder->linear->weight.scalar_type();
  const auto opts = x_embedder->linear->weight.options();
  auto keep = [&](const std::string& name, const torch::Tensor& t) {
    if (capture != nullptr) (*capture)[name] = t;
  };

  // Input assembly: [latent, condition mask, padding mask] -> patches [B, T, Hp, Wp, C·p·p].
  DOJO_CHECK(in.condition_mask.defined() && in.condition_mask.dim() == 5 && in.condition_mask.size(1) == 1,
             "DiT: condition_mask must be [B, 1, T, H, W]");
  std::vector<torch::Tensor> parts = {in.x.to(dtype), in.condition_mask.to(dtype).expand({B, 1, T, H, W})};
  if (c.concat_padding_mask) {
    torch::Tensor pad =
        in.padding_mask.defined() ? in.padding_mask.to(dtype) : torch::zeros({B, 1, H, W}, opts);
    DOJO_CHECK(pad.dim() == 4 && pad.size(1) == 1, "DiT: padding_mask must be [B, 1, H, W]");
    if (pad.size(2) != H || pad.size(3) != W)
      pad = torch::nn::functional::interpolate(pad, torch::nn::functional::InterpolateFuncOptions()
                                                        .size(std::vector<int64_t>{H, W})
                                                        .mode(torch::kNearest));
    parts.push_back(pad.unsqueeze(2).expand({B, 1, T, H, W}));
  }
  const auto x_in = torch::cat(parts, 1);  // [B, C, T, H, W]
  const int64_t C = x_in.size(1);
  const auto patches = x_in.view({B, C, T, Hp, p, Wp, p})
                           .permute({0, 2, 3, 5, 1, 4, 6})  // b t hp wp c m n (channel-major)
                           .reshape({B, T, Hp, Wp, C * p * p});
  auto x = x_embedder->linear(patches);  // [B, T, Hp, Wp, D]
  keep("x_embedded", x);

  // RoPE for absolute frames [frame_offset, frame_offset + T), unless given.
  torch::Tensor cos = in.rope_cos, sin = in.rope_sin;  // [L, 1, d]
  if (cos.defined() || sin.defined()) {
    const int64_t head_dim = D / c.num_heads;
    DOJO_CHECK(cos.defined() && sin.defined() && cos.dim() == 3 && cos.size(0) == L && cos.size(1) == 1 &&
                   cos.size(2) == head_dim && sin.sizes() == cos.sizes(),
               "DiT: rope_cos and rope_sin must both be [" + std::to_string(L) + ", 1, " +
                   std::to_string(head_dim) + "]");
  } else {
    const auto angles =
        rope_angles_3d(pos_embedder->dim_spatial_range, pos_embedder->dim_temporal_range, T, Hp, Wp,
                       in.frame_offset, c.rope_h_extrapolation_ratio, c.rope_w_extrapolation_ratio,
                       c.rope_t_extrapolation_ratio);  // [L, 1, 1, d]
    keep("rope_emb", angles);
    const auto angles_L_1_d = angles.flatten(1, 2);
    cos = angles_L_1_d.cos();
    sin = angles_L_1_d.sin();
  }

  // Text context.
  torch::Tensor context;  // [B, Lc, C]
  if (in.projected_context.defined()) {
    DOJO_CHECK(in.projected_context.dim() == 3 && in.projected_context.size(2) == c.crossattn_dim(),
               "DiT: projected_context must be [B, L, " + std::to_string(c.crossattn_dim()) + "]");
    context = in.projected_context.to(dtype);
  } else {
    context = project_context(in.context.defined() ? in.context
                                                   : torch::zeros({B, 1, c.crossattn_emb_channels}, opts));
  }
  keep("crossattn_proj_out", context);

  // Timesteps -> sinusoid [B, T_t, D] and adaLN-LoRA [B, T_t, 3D] (float32).
  DOJO_CHECK(in.timesteps.defined(), "DiT: timesteps are required");
  auto ts = in.timesteps.dim() == 1 ? in.timesteps.unsqueeze(1) : in.timesteps;
  DOJO_CHECK(ts.dim() == 2 && ts.size(0) == B && (ts.size(1) == 1 || ts.size(1) == T),
             "DiT: timesteps must be [B, 1] or [B, T]");
  const auto t_emb_raw =
      timestep_sinusoid(ts.to(torch::kFloat32) * c.timestep_scale, D).to(dtype);  // [B, T_t, D]
  auto adaln_lora = t_embedding(t_emb_raw);                                       // [B, T_t, 3D]
  keep("t_emb_raw", t_emb_raw);
  keep("adaln_lora_raw", adaln_lora);

  // Actions: 4 per latent frame; the first frame of a sequence (frame 0) has none.
  auto t_emb = t_emb_raw;
  const int64_t lead = in.frame_offset == 0 ? 1 : 0;
  const auto actions = in.actions.defined() && !c.action_scale.empty()
                           ? in.actions * action_scale_on(in.actions.options())
                           : in.actions;
  const int64_t action_frames = T - lead;
  if (actions.defined() && c.whole_clip_actions > 0) {
    DOJO_CHECK(actions.dim() == 3 && actions.size(0) == B && actions.size(1) == c.whole_clip_actions &&
                   actions.size(2) == c.action_dim,
               "DiT: actions must be [B, " + std::to_string(c.whole_clip_actions) + ", " +
                   std::to_string(c.action_dim) + "] (whole-clip injection)");
    const auto row = actions.to(dtype).reshape({B, 1, c.whole_clip_actions * c.action_dim});  // [B, 1, NA]
    t_emb = t_emb + action_embedder_B_D(row);             // [B, T_t, D], the same for every frame
    adaln_lora = adaln_lora + action_embedder_B_3D(row);  // [B, T_t, 3D]
  } else if ((actions.defined() || in.action_embedding.defined()) && action_frames > 0) {
    const int64_t k = c.actions_per_latent_frame;
    DOJO_CHECK(
        !actions.defined() || (actions.dim() == 3 && actions.size(0) == B &&
                               actions.size(1) == k * action_frames && actions.size(2) == c.action_dim),
        "DiT: actions must be [B, " + std::to_string(k * action_frames) + ", " +
            std::to_string(c.action_dim) + "] for " + std::to_string(T) + " latent frames at frame_offset " +
            std::to_string(in.frame_offset));
    const auto embedded =
        in.action_embedding.defined() ? in.action_embedding : embed_actions(in.actions, action_frames);
    // In the dtype the MLPs gave (bf16 under autocast), as the sums below always saw them.
    auto emb_D = embedded.to_t_emb;        // [B, T', D]
    auto emb_3D = embedded.to_adaln_lora;  // [B, T', 3D]
    DOJO_CHECK(emb_D.dim() == 3 && emb_D.size(0) == B && emb_D.size(1) == action_frames &&
                   emb_D.size(2) == D && emb_3D.dim() == 3 && emb_3D.size(1) == action_frames &&
                   emb_3D.size(2) == 3 * D,
               "DiT: the action embedding must be [B, " + std::to_string(action_frames) + ", D] and [B, " +
                   std::to_string(action_frames) + ", 3D] for this call");
    keep("action_emb_B_D", emb_D);
    keep("action_emb_B_3D", emb_3D);
    if (lead > 0) {
      emb_D = torch::cat({torch::zeros({B, lead, D}, opts), emb_D}, 1);        // [B, T, D]
      emb_3D = torch::cat({torch::zeros({B, lead, 3 * D}, opts), emb_3D}, 1);  // [B, T, 3D]
    }
    t_emb = t_emb + emb_D;
    adaln_lora = adaln_lora + emb_3D;
  }
  t_emb = t_embedding_norm(t_emb);  // [B, T or 1, D]
  keep("t_emb_normed", t_emb);

  DitBlockContext ctx;
  ctx.silu_emb = torch::silu(t_emb);  // every modulation MLP starts with SiLU(t_emb)
  ctx.adaln_lora = adaln_lora;
  ctx.cos = cos;
  ctx.sin = sin;
  ctx.context = context;
  ctx.mask = in.self_attn_mask;
  ctx.store_kv = in.store_kv;
  if (in.kv_cache != nullptr)
    DOJO_CHECK(static_cast<int64_t>(in.kv_cache->size()) == c.num_blocks,
               "DiT: kv_cache must hold one entry per block (" + std::to_string(c.num_blocks) + ")");

  x = x.view({B, T, S, D});
  const bool recompute = recompute_blocks && torch::GradMode::is_enabled() && in.kv_cache == nullptr;
  for (int64_t i = 0; i < c.num_blocks; ++i) {
    ctx.cache = in.kv_cache != nullptr ? &(*in.kv_cache)[i] : nullptr;
    x = recompute ? RecomputedBlock::apply(x, ctx.silu_emb, ctx.adaln_lora, ctx.context, ctx.cos, ctx.sin,
                                           ctx.mask.defined() ? ctx.mask : RecomputedBlock::no_mask(),
                                           reinterpret_cast<int64_t>(block_list[i].get()))
                  : block_list[i]->forward(x, ctx);  // [B, T, S, D]
    if (capture != nullptr) keep("block" + std::to_string(i) + "_out", x.reshape({B, L, D}));
  }

  // Final layer: adaLN with (shift, scale) from the first 2D LoRA channels, then D -> p·p·16.
  const auto fm = (final_layer->adaln_modulation(ctx.silu_emb) + adaln_lora.slice(-1, 0, 2 * D))
                      .unsqueeze(2)
                      .chunk(2, -1);
  auto out = final_layer->linear(modulate(x, fm[0], fm[1]));  // [B, T, S, p·p·16]
  out = out.view({B, T, Hp, Wp, out.size(-1)});
  keep("final_layer_out", out);

  // Unpatchify "B T H W (p1 p2 t C) -> B C (T t) (H p1) (W p2)" (channel-minor).
  const int64_t Co = c.out_channels;
  return out.view({B, T, Hp, Wp, p, p, Co})
      .permute({0, 6, 1, 2, 4, 3, 5})  // B C T Hp p1 Wp p2
      .reshape({B, Co, T, H, W});
}

torch::Tensor denoise_velocity(ActionDitImpl& net, const DitInputs& base, const torch::Tensor& x_t,
                               const torch::Tensor& gt_x0, const torch::Tensor& noise,
                               const torch::Tensor& condition_mask) {
  const auto m = condition_mask.to(x_t.scalar_type());  // [B, 1, T, H, W], broadcast over channels
  DitInputs in = base;
  in.x = gt_x0 * m + x_t * (1 - m);
  in.condition_mask = condition_mask;
  const auto v = net.forward(in);
  return (noise - gt_x0) * m + v * (1 - m);
}

}  // namespace dojo::models
