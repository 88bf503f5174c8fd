#include "models/lam.h"

#include <cmath>

#include "core/autocast.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/state_dict.h"
#include "io/frame_ops.h"
#include "models/attention.h"
#include "models/dit_kernels.h"
#include "models/lam_kernels.h"

namespace dojo::models {

namespace nn = torch::nn;

// ---------------------------------------------------------------------------------------------
// Config

LamConfig LamConfig::released() { return LamConfig{}; }

LamConfig LamConfig::tiny() {
  LamConfig c;
  c.model_dim = 64;
  c.patch_size = 8;
  c.enc_blocks = 2;
  c.dec_blocks = 2;
  c.num_heads = 4;
  c.height = 48;
  c.width = 64;
  return c;
}

LamConfig LamConfig::small() {
  LamConfig c = tiny();
  c.model_dim = 128;
  c.enc_blocks = 3;
  c.dec_blocks = 3;
  return c;
}

nlohmann::json LamConfig::to_json() const {
  return {{"model", "lam"},
          {"in_dim", in_dim},
          {"model_dim", model_dim},
          {"latent_dim", latent_dim},
          {"patch_size", patch_size},
          {"enc_blocks", enc_blocks},
          {"dec_blocks", dec_blocks},
          {"num_heads", num_heads},
          {"dropout", dropout},
          {"height", height},
          {"width", width}};
}

LamConfig LamConfig::from_json(const nlohmann::json& j) {
  LamConfig c;
  const JsonFields f(j, "LAM config");
  f.get("in_dim", c.in_dim);
  f.get("model_dim", c.model_dim);
  f.get("latent_dim", c.latent_dim);
  f.get("patch_size", c.patch_size);
  f.get("enc_blocks", c.enc_blocks);
  f.get("dec_blocks", c.dec_blocks);
  f.get("num_heads", c.num_heads);
  f.get("height", c.height);
  f.get("width", c.width);
  f.get("dropout", c.dropout);
  c.validate();
  return c;
}

void LamConfig::validate() const {
  auto positive = [](const char* field, int64_t v) { check_positive("LAM config", field, v); };
  positive("in_dim", in_dim);
  positive("model_dim", model_dim);
  positive("latent_dim", latent_dim);
  positive("patch_size", patch_size);
  positive("enc_blocks", enc_blocks);
  positive("dec_blocks", dec_blocks);
  positive("num_heads", num_heads);
  positive("height", height);
  positive("width", width);
  DOJO_CHECK(model_dim % num_heads == 0, "LAM config: 'model_dim' must be divisible by 'num_heads'");
  DOJO_CHECK(head_dim() % 2 == 0, "LAM config: head dim (model_dim / num_heads) must be even for rotary");
  DOJO_CHECK(model_dim % 2 == 0, "LAM config: 'model_dim' must be even");
  DOJO_CHECK(height % patch_size == 0 && width % patch_size == 0,
             "LAM config: 'height' and 'width' must be multiples of 'patch_size'");
  DOJO_CHECK(dropout >= 0.0 && dropout < 1.0, "LAM config: 'dropout' must be in [0, 1)");
}

// ---------------------------------------------------------------------------------------------
// Helpers

torch::Tensor lam_patchify(const torch::Tensor& videos, int64_t size) {
  TORCH_CHECK(videos.dim() == 5, "lam_patchify: expected [B, T, H, W, C], got ", videos.sizes());
  const int64_t B = videos.size(0), T = videos.size(1), C = videos.size(4);
  const int64_t hn = videos.size(2) / size, wn = videos.size(3) / size;
  auto v = videos.slice(2, 0, hn * size).slice(3, 0, wn * size);  // crop to multiples of size
  v = v.reshape({B, T, hn, size, wn, size, C});                   // b t hn hp wn wp c
  return v.permute({0, 1, 2, 4, 3, 5, 6}).reshape({B, T, hn * wn, size * size * C});
}

torch::Tensor lam_unpatchify(const torch::Tensor& patches, int64_t size, int64_t h_out, int64_t w_out) {
  const int64_t B = patches.size(0), T = patches.size(1);
  const int64_t hn = (h_out + size - 1) / size, wn = patches.size(2) / hn;
  const int64_t C = patches.size(3) / (size * size);
  auto x = patches.reshape({B, T, hn, wn, size, size, C});  // b t hn wn hp wp c
  x = x.permute({0, 1, 2, 4, 3, 5, 6}).reshape({B, T, hn * size, wn * size, C});
  return x.slice(2, 0, h_out).slice(3, 0, w_out);
}

torch::Tensor lam_sinusoidal_table(int64_t len, int64_t dim) {
  // Float32 arithmetic in the same order as the reference so the table matches bit for bit.
  auto pe = torch::zeros({len, dim});
  auto position = torch::arange(0, len, torch::kFloat).unsqueeze(1);  // [len, 1]
  auto exponent = torch::arange(0, dim, 2, torch::kFloat) * (-(std::log(10000.0) / dim));
  auto div_term = torch::exp(exponent);  // [dim / 2]
  pe.slice(1, 0, dim, 2).copy_(torch::sin(position * div_term));
  pe.slice(1, 1, dim, 2).copy_(torch::cos(position * div_term));
  return pe;
}

// ---------------------------------------------------------------------------------------------
// Modules

LamRotaryImpl::LamRotaryImpl(int64_t dim) {
  auto f = 1.0 / torch::pow(10000.0, torch::arange(0, dim, 2, torch::kFloat).slice(0, 0, dim / 2) / dim);
  freqs = register_parameter("freqs", f, /*requires_grad=*/false);
}

torch::Tensor LamRotaryImpl::rotate(const torch::Tensor& x) const {
  // Computed in float32 (the reference disables autocast here).
  const int64_t n = x.size(-2), d = x.size(-1);
  auto xf = x.to(torch::kFloat);
  auto pos = torch::arange(n, xf.options());
  auto angles = pos.unsqueeze(1) * freqs.to(xf.device()).unsqueeze(0);  // [n, d / 2]
  angles = angles.repeat_interleave(2, /*dim=*/1);                      // [n, d]: (f0 f0 f1 f1 ...)
  auto cos = angles.cos(), sin = angles.sin();
  // rotate_half on interleaved pairs: (x0, x1) -> (-x1, x0)
  auto pairs = xf.reshape({-1, n, d / 2, 2});
  auto rot = torch::stack({-pairs.select(-1, 1), pairs.select(-1, 0)}, -1).reshape(xf.sizes());
  return (xf * cos + rot * sin).to(x.scalar_type());
}

LamSelfAttentionImpl::LamSelfAttentionImpl(int64_t dim, int64_t heads_, double dropout, bool rotary)
    : heads(heads_) {
  to_q = register_module("to_q", nn::Linear(nn::LinearOptions(dim, dim).bias(false)));
  to_k = register_module("to_k", nn::Linear(nn::LinearOptions(dim, dim).bias(false)));
  to_v = register_module("to_v", nn::Linear(nn::LinearOptions(dim, dim).bias(false)));
  to_out = register_module("to_out", nn::Sequential(nn::Linear(dim, dim), nn::Dropout(dropout)));
  if (rotary) rotary_embedding = register_module("rotary_embedding", LamRotary(dim / heads));
}

torch::Tensor LamSelfAttentionImpl::project_qkv(const torch::Tensor& x) {
  // One product for the three projections: three of [L, E] x [E, E] on 2 cores spend as long
  // waking the BLAS threads as multiplying (the weights stay three parameters, as released).
  return torch::linear(x, torch::cat({to_q->weight, to_k->weight, to_v->weight}));
}

torch::Tensor LamSelfAttentionImpl::forward(const torch::Tensor& x) {
  const int64_t N = x.size(0), L = x.size(1), E = x.size(2), D = E / heads;
  auto split = [&](const torch::Tensor& t) {
    return t.view({N, L, heads, D}).transpose(1, 2);
  };  // [N, h, L, D]
  const auto qkv = project_qkv(x).chunk(3, -1);
  auto q = split(qkv[0]), k = split(qkv[1]), v = split(qkv[2]);
  if (rotary_embedding) {
    q = rotary_embedding->rotate(q);
    k = rotary_embedding->rotate(k);
  }
  auto o = attention(q, k, v, std::nullopt, false, 1.0 / std::sqrt(static_cast<double>(D)));  // [N, h, L, D]
  return to_out->forward(o.transpose(1, 2).reshape({N, L, E}));
}

torch::Tensor LamSelfAttentionImpl::forward_along_axis1(const torch::Tensor& x) {
  const int64_t G = x.size(0), L = x.size(1), R = x.size(2), E = x.size(3), D = E / heads;
  // Not under CPU autocast at all: the projections would hand the kernel bf16.
  if (L <= kShortAttentionMaxLength && fused_dit_kernels_apply({x, to_q->weight}) &&
      !AutocastGuard::is_enabled(c10::DeviceType::CPU)) {
    const auto qkv = project_qkv(x);  // [G, L, R, 3E]
    const auto freqs = rotary_embedding ? rotary_embedding->freqs : torch::Tensor();
    const auto o = short_attention_fused(qkv, heads, freqs, 1.0 / std::sqrt(static_cast<double>(D)));
    return to_out->forward(o);  // [G, L, R, E]
  }
  const auto y = forward(x.transpose(1, 2).reshape({G * R, L, E}));  // [(G R), L, E]
  return y.view({G, R, L, E}).transpose(1, 2);
}

static nn::Sequential make_ffn(int64_t dim, double dropout) {
  // Indices 0..3 as released: Linear, GELU (exact), Dropout, Linear.
  return nn::Sequential(nn::Linear(dim, dim * 4), nn::GELU(), nn::Dropout(dropout), nn::Linear(dim * 4, dim));
}

static LamLayerNorm make_norm(int64_t dim) { return LamLayerNorm(dim); }

LamSpatioTemporalBlockImpl::LamSpatioTemporalBlockImpl(int64_t dim, int64_t heads, double dropout) {
  spatial_attn = register_module("spatial_attn", LamSelfAttention(dim, heads, dropout, false));
  temporal_attn = register_module("temporal_attn", LamSelfAttention(dim, heads, dropout, true));
  ffn = register_module("ffn", make_ffn(dim, dropout));
  norm1 = register_module("norm1", make_norm(dim));
  norm2 = register_module("norm2", make_norm(dim));
  norm3 = register_module("norm3", make_norm(dim));
}

torch::Tensor LamSpatioTemporalBlockImpl::forward(const torch::Tensor& input) {
  const int64_t B = input.size(0), T = input.size(1), S = input.size(2), E = input.size(3);
  // Spatial: each frame of each sample on its own.
  auto x = input.reshape({B * T, S, E});  // [(B T), S, E]
  x = x + spatial_attn(norm1(x));
  // Temporal: each token position of each sample on its own.
  x = x.view({B, T, S, E});
  x = x + temporal_attn->forward_along_axis1(norm2(x));  // [B, T, S, E]
  return x + ffn->forward(norm3(x));
}

LamSpatioBlockImpl::LamSpatioBlockImpl(int64_t dim, int64_t heads, double dropout) {
  spatial_attn = register_module("spatial_attn", LamSelfAttention(dim, heads, dropout, false));
  ffn = register_module("ffn", make_ffn(dim, dropout));
  norm1 = register_module("norm1", make_norm(dim));
  norm2 = register_module("norm2", make_norm(dim));
}

torch::Tensor LamSpatioBlockImpl::forward(const torch::Tensor& input) {
  const int64_t B = input.size(0), T = input.size(1), S = input.size(2), E = input.size(3);
  auto x = input.reshape({B * T, S, E});  // [(B T), S, E]
  x = x + spatial_attn(norm1(x));
  x = x.view({B, T, S, E});
  return x + ffn->forward(norm2(x));
}

LamTransformerImpl::LamTransformerImpl(int64_t in_dim, int64_t model_dim, int64_t out_dim, int64_t blocks,
                                       int64_t heads, double dropout, bool temporal_)
    : temporal(temporal_) {
  ffn = register_module(
      "ffn", nn::Sequential(make_norm(in_dim), nn::Linear(in_dim, model_dim), make_norm(model_dim)));
  transformer_blocks = register_module("transformer_blocks", nn::ModuleList());
  for (int64_t i = 0; i < blocks; ++i) {
    if (temporal)
      transformer_blocks->push_back(LamSpatioTemporalBlock(model_dim, heads, dropout));
    else
      transformer_blocks->push_back(LamSpatioBlock(model_dim, heads, dropout));
  }
  out = register_module("out", nn::Linear(model_dim, out_dim));
}

torch::Tensor LamTransformerImpl::forward(const torch::Tensor& input) {
  auto x = ffn->forward(input);  // [B, T, S, E]
  // Position encoding over the token axis, shared by every frame and sample.
  x = x + lam_sinusoidal_table(x.size(2), x.size(3)).to(x.options());
  for (auto& m : *transformer_blocks) {
    if (temporal)
      x = m->as<LamSpatioTemporalBlockImpl>()->forward(x);
    else
      x = m->as<LamSpatioBlockImpl>()->forward(x);
  }
  return out(x);
}

LatentActionModelImpl::LatentActionModelImpl(const LamConfig& cfg) : config(cfg) {
  config.validate();
  const int64_t P = config.patch_dim(), E = config.model_dim;
  action_prompt = register_parameter("action_prompt", torch::empty({1, 1, 1, P}).uniform_(-1, 1));
  encoder = register_module("encoder", LamTransformer(P, E, E, config.enc_blocks, config.num_heads,
                                                      config.dropout, /*temporal=*/true));
  fc = register_module("fc", nn::Linear(E, config.latent_dim * 2));
  patch_up = register_module("patch_up", nn::Linear(P, E));
  action_up = register_module("action_up", nn::Linear(config.latent_dim, E));
  decoder = register_module("decoder", LamTransformer(E, E, P, config.dec_blocks, config.num_heads,
                                                      config.dropout, /*temporal=*/false));
}

LamOutput LatentActionModelImpl::encode(const torch::Tensor& videos) {
  DOJO_CHECK(videos.dim() == 5 && videos.size(1) >= 2 && videos.size(4) == config.in_dim,
             "LAM: expected videos [B, T >= 2, H, W, " + std::to_string(config.in_dim) + "]");
  const int64_t B = videos.size(0), T = videos.size(1);
  LamOutput out;
  out.patches = lam_patchify(videos, config.patch_size);  // [B, T, N, P]
  auto prompt = action_prompt.expand({B, T, 1, action_prompt.size(3)});
  auto z = encoder(torch::cat({prompt, out.patches}, 2));  // [B, T, 1+N, E]
  // The prompt token of every frame after the first carries the action that led to it.
  z = z.slice(1, 1).select(2, 0).reshape({B * (T - 1), config.model_dim});  // [(B T-1), E]
  auto moments = fc(z);                                                     // [(B T-1), 2L]
  auto chunks = moments.chunk(2, 1);
  out.z_mu = chunks[0];
  out.z_logvar = chunks[1];
  auto rep =
      is_training() ? out.z_mu + torch::randn_like(out.z_logvar) * torch::exp(0.5 * out.z_logvar) : out.z_mu;
  out.z_rep = rep.reshape({B, T - 1, 1, config.latent_dim});
  return out;
}

torch::Tensor LatentActionModelImpl::decode(const torch::Tensor& frames, const torch::Tensor& z) {
  const int64_t H = frames.size(2), W = frames.size(3);
  auto patches = lam_patchify(frames, config.patch_size);  // [B, T', N, P]
  auto x = patch_up(patches) + action_up(z);               // [B, T', N, E] (+ [B, T', 1, E])
  auto y = torch::sigmoid(decoder(x));                     // [B, T', N, P]
  return lam_unpatchify(y, config.patch_size, H, W);       // [B, T', H, W, C]
}

LamOutput LatentActionModelImpl::forward(const torch::Tensor& videos) {
  auto out = encode(videos);
  const int64_t H = videos.size(2), W = videos.size(3);
  auto x = patch_up(out.patches.slice(1, 0, -1)) + action_up(out.z_rep);  // [B, T-1, N, E]
  auto y = torch::sigmoid(decoder(x));
  out.recon = lam_unpatchify(y, config.patch_size, H, W);  // [B, T-1, H, W, C]
  return out;
}

torch::Tensor lam_latent_actions(LatentActionModel& model, const torch::Tensor& lam_video,
                                 bool published_order) {
  DOJO_CHECK(lam_video.dim() == 5 && lam_video.size(1) % 2 == 0,
             "LAM: expected lam_video [B, 2P, H, W, C] (P frame pairs per sample)");
  const int64_t B = lam_video.size(0), P = lam_video.size(1) / 2;
  // "b (p t) h w c -> (b p) t h w c": a contiguous reshape keeps rows in (b p) order.
  auto pairs = lam_video.reshape({B * P, 2, lam_video.size(2), lam_video.size(3), lam_video.size(4)});
  auto mu = model->encode(pairs).z_mu;  // [(B P), L], row b * P + p
  const int64_t L = mu.size(1);
  if (!published_order) return mu.reshape({B, P, L});  // "(b p) d -> b p d"
  // Released wrapper: "(t b) d -> b t d" with t = P, reading row t * B + b.
  return mu.reshape({P, B, L}).transpose(0, 1).contiguous();
}

double lam_forward_flops(const LamConfig& c) {
  const double E = static_cast<double>(c.model_dim), P = static_cast<double>(c.patch_dim());
  const double N = static_cast<double>((c.height / c.patch_size) * (c.width / c.patch_size));
  const double S = N + 1, T = 2;  // encoder tokens per frame (prompt + patches), frames
  const double enc_tokens = T * S;
  double f = 0;
  f += enc_tokens * 2 * P * E;                                            // encoder ffn.1
  f += c.enc_blocks * (enc_tokens * (8 * E * E + 8 * E * E + 16 * E * E)  // spatial + temporal proj, FFN
                       + T * 4 * S * S * E                                // spatial scores + values
                       + S * 4 * T * T * E);                              // temporal scores + values
  f += enc_tokens * 2 * E * E;                                            // encoder out
  f += 2 * E * 2 * c.latent_dim;                                          // fc (one latent per pair)
  f += N * (2 * P * E + 2 * c.latent_dim * E + 2 * E * E);  // patch_up, action_up, decoder ffn.1
  f += c.dec_blocks * (N * (8 * E * E + 16 * E * E) + 4 * N * N * E);
  f += N * 2 * E * P;  // decoder out
  return f;
}

LamLoss lam_loss(const LamOutput& out, const torch::Tensor& videos, double beta) {
  LamLoss l;
  auto target = videos.slice(1, 1);
  l.mse = (target - out.recon).pow(2).mean();
  auto kl_per_sample = -0.5 * (1 + out.z_logvar - out.z_mu.pow(2) - out.z_logvar.exp()).sum(1);  // [(B T-1)]
  l.kl = kl_per_sample.mean();
  l.total = l.mse + beta * l.kl;
  return l;
}

// ---------------------------------------------------------------------------------------------
// Inputs and checkpoints

torch::Tensor to_unit_float(const torch::Tensor& video) {
  if (video.scalar_type() == torch::kByte) return video.to(torch::kFloat).div_(255.0);
  return video.to(torch::kFloat);
}

torch::Tensor lam_encode_episode(LatentActionModel& model, const torch::Tensor& frames, int64_t batch_pairs) {
  torch::NoGradGuard no_grad;
  model->eval();
  const auto& c = model->config;
  auto f = frames;
  if (f.size(1) != c.height || f.size(2) != c.width) f = io::resize_center_crop(f, c.height, c.width);
  const auto video = to_unit_float(f);  // [T, h, w, 3]
  const int64_t T = video.size(0);
  std::vector<torch::Tensor> out;
  for (int64_t s = 0; s < T - 1; s += batch_pairs) {
    const int64_t e = std::min(T - 1, s + batch_pairs);
    auto pairs = torch::stack({video.slice(0, s, e), video.slice(0, s + 1, e + 1)}, 1);  // [n, 2, h, w, 3]
    out.push_back(model->encode(pairs).z_mu);
  }
  return out.empty() ? torch::zeros({0, c.latent_dim}) : torch::cat(out, 0);  // [T - 1, latent]
}

CheckpointData lam_checkpoint(const LatentActionModelImpl& model) {
  CheckpointData data;
  data.config = model.config.to_json();
  for (const auto& [name, t] : state_dict(model)) data.model.emplace_back("lam." + name, t);
  return data;
}

LatentActionModel load_lam(const std::filesystem::path& dir) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  LatentActionModel model(LamConfig::from_json(ckpt.config()));
  LoadOptions opts;
  opts.prefix = "lam.";
  load_state_dict(*model, ckpt.model(), opts);  // strict: a mismatch throws, naming the tensors
  model->eval();
  return model;
}

}  // namespace dojo::models
