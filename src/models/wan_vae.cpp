#include "models/wan_vae.h"

#include <algorithm>
#include <cmath>
#include <string>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/state_dict.h"
#include "models/attention.h"

namespace dojo::models {

namespace {

constexpr int64_t kCacheT = 2;  // frames of history a 3x3x3 causal conv needs

torch::Tensor last_frames(const torch::Tensor& x, int64_t n) {  // [B, C, min(n, T), H, W]
  const int64_t t = x.size(2);
  return x.narrow(2, std::max<int64_t>(0, t - n), std::min(n, t));
}

// [B, C, T, H, W] <-> [B*T, C, H, W] (per-frame 2-D ops).
torch::Tensor fold_time(const torch::Tensor& x) {
  return x.permute({0, 2, 1, 3, 4}).reshape({x.size(0) * x.size(2), x.size(1), x.size(3), x.size(4)});
}
torch::Tensor unfold_time(const torch::Tensor& x, int64_t b) {
  const int64_t t = x.size(0) / b;
  return x.reshape({b, t, x.size(1), x.size(2), x.size(3)}).permute({0, 2, 1, 3, 4});
}

// A 3x3x3 causal conv run through the cache rule: the cache keeps the last 2 input frames
// (topped up from the previous cache when the chunk has only 1 frame) and replaces the zero
// left padding of the next chunk.
torch::Tensor cached_conv(CausalConv3dImpl& conv, const torch::Tensor& x, WanVaeCache* cache) {
  if (cache == nullptr) return conv.forward(x);
  auto& slot = cache->next();
  auto cache_x = last_frames(x, kCacheT).clone();
  const bool has = slot.state == WanVaeCache::State::kTensor;
  if (cache_x.size(2) < kCacheT && has) cache_x = torch::cat({last_frames(slot.x, 1), cache_x}, 2);
  auto out = conv.forward(x, has ? slot.x : torch::Tensor());
  slot.state = WanVaeCache::State::kTensor;
  slot.x = cache_x;
  return out;
}

void init_conv(torch::Tensor& weight, torch::Tensor& bias, int64_t fan_in) {
  // PyTorch's default Conv init: kaiming_uniform(a=sqrt(5)) == U(-1/sqrt(fan_in), 1/sqrt(fan_in)).
  torch::NoGradGuard no_grad;
  const double bound = 1.0 / std::sqrt(static_cast<double>(fan_in));
  weight.uniform_(-bound, bound);
  if (bias.defined()) bias.uniform_(-bound, bound);
}

}  // namespace

// --- config --------------------------------------------------------------------------------

WanVaeConfig WanVaeConfig::tiny() {
  WanVaeConfig c;
  c.dim = 8;
  return c;
}

int64_t WanVaeConfig::spatial_factor() const { return int64_t{1} << (dim_mult.size() - 1); }

int64_t WanVaeConfig::temporal_factor() const {
  int64_t f = 1;
  for (bool t : temperal_downsample) f *= t ? 2 : 1;
  return f;
}

nlohmann::json WanVaeConfig::to_json() const {
  return {{"dim", dim},
          {"z_dim", z_dim},
          {"dim_mult", dim_mult},
          {"num_res_blocks", num_res_blocks},
          {"attn_scales", attn_scales},
          {"temperal_downsample", temperal_downsample},
          {"dropout", dropout},
          {"latent_mean", latent_mean},
          {"latent_std", latent_std}};
}

WanVaeConfig WanVaeConfig::from_json(const nlohmann::json& j) {
  WanVaeConfig c;
  auto get = [&](const char* key, auto& field) {
    if (!j.contains(key)) return;
    try {
      j.at(key).get_to(field);
    } catch (const std::exception& e) {
      throw Error(std::string("WanVaeConfig: bad field '") + key + "': " + e.what());
    }
  };
  get("dim", c.dim);
  get("z_dim", c.z_dim);
  get("dim_mult", c.dim_mult);
  get("num_res_blocks", c.num_res_blocks);
  get("attn_scales", c.attn_scales);
  get("temperal_downsample", c.temperal_downsample);
  get("dropout", c.dropout);
  get("latent_mean", c.latent_mean);
  get("latent_std", c.latent_std);
  DOJO_CHECK(c.dim > 0 && c.z_dim > 0, "WanVaeConfig: 'dim' and 'z_dim' must be positive");
  DOJO_CHECK(c.dim_mult.size() >= 2, "WanVaeConfig: 'dim_mult' needs at least 2 entries");
  DOJO_CHECK(c.temperal_downsample.size() == c.dim_mult.size() - 1,
             "WanVaeConfig: 'temperal_downsample' must have len(dim_mult) - 1 entries");
  DOJO_CHECK(c.latent_mean.size() == static_cast<size_t>(c.z_dim) &&
                 c.latent_std.size() == static_cast<size_t>(c.z_dim),
             "WanVaeConfig: 'latent_mean'/'latent_std' must have z_dim entries");
  return c;
}

void init_frame_by_frame(WanVae& vae) {
  torch::NoGradGuard no_grad;
  for (const auto& module : vae->modules()) {
    if (auto* resample = dynamic_cast<ResampleImpl*>(module.get()); resample && resample->time_conv) {
      // time_conv kernels are [out, in, 3, 1, 1]: identity on the newest tap. Upsampling has
      // out = 2 * in (the two output frames), so both halves copy the input frame.
      auto& weight = resample->time_conv->weight;
      const int64_t in = weight.size(1), newest = weight.size(2) - 1;
      weight.zero_();
      resample->time_conv->bias.zero_();
      for (int64_t o = 0; o < weight.size(0); o += in)
        weight.narrow(0, o, in).select(2, newest).select(2, 0).select(2, 0).copy_(
            torch::eye(in));  // [in, in]
    }
  }
  for (const auto& module : vae->modules()) {
    auto* conv = dynamic_cast<CausalConv3dImpl*>(module.get());
    // Spatio-temporal convs (not the time_convs above, which have 1x1 spatial kernels).
    if (conv && conv->kernel[0] > 1 && conv->kernel[1] > 1)
      conv->weight.narrow(2, 0, conv->kernel[0] - 1).zero_();  // [out, in, past taps, kh, kw]
  }
}

int64_t WanVaeCache::bytes() const {
  int64_t n = 0;
  for (const auto& s : slots)
    if (s.x.defined()) n += s.x.numel() * static_cast<int64_t>(s.x.element_size());
  return n;
}

// --- blocks --------------------------------------------------------------------------------

CausalConv3dImpl::CausalConv3dImpl(int64_t in, int64_t out, std::vector<int64_t> kernel_,
                                   std::vector<int64_t> stride_, std::vector<int64_t> padding_)
    : kernel(std::move(kernel_)), stride(std::move(stride_)), padding(std::move(padding_)) {
  weight = register_parameter("weight", torch::empty({out, in, kernel[0], kernel[1], kernel[2]}));
  bias = register_parameter("bias", torch::empty({out}));
  reset_parameters();
}

void CausalConv3dImpl::reset_parameters() {
  init_conv(weight, bias, weight.size(1) * kernel[0] * kernel[1] * kernel[2]);
}

torch::Tensor CausalConv3dImpl::forward(const torch::Tensor& x, const torch::Tensor& cache) {
  int64_t pad_t = 2 * padding[0];
  torch::Tensor in = x;  // [B, C, T, H, W]
  if (cache.defined() && pad_t > 0) {
    in = torch::cat({cache.to(x.device(), x.scalar_type()), x}, 2);  // [B, C, c + T, H, W]
    pad_t -= cache.size(2);
  }
  // A single frame with nothing cached sees only zeros through the past taps, so only the
  // current-frame tap contributes: the same result from a third of the work (image batches,
  // the first frame of every stream).
  const bool single_frame = !cache.defined() && !conv3d_reference_path() && x.size(2) == 1 &&
                            stride[0] == 1 && pad_t == kernel[0] - 1;
  if (single_frame)
    return torch::conv3d(x, weight.narrow(2, kernel[0] - 1, 1), bias, stride,
                         {0, padding[1], padding[2]});  // [B, out, 1, H', W']
  if (pad_t > 0 || padding[1] > 0 || padding[2] > 0)
    in = torch::constant_pad_nd(in, {padding[2], padding[2], padding[1], padding[1], pad_t, 0});
  return torch::conv3d(in, weight, bias, stride);  // [B, out, T', H', W']
}

bool& conv3d_reference_path() {
  static bool reference = false;
  return reference;
}

RmsNormImpl::RmsNormImpl(int64_t dim, bool images) : scale(std::sqrt(static_cast<double>(dim))) {
  gamma = register_parameter("gamma", images ? torch::ones({dim, 1, 1}) : torch::ones({dim, 1, 1, 1}));
}

torch::Tensor RmsNormImpl::forward(const torch::Tensor& x) {
  // x / max(||x||, 1e-12) as F.normalize, written as a sum of squares: aten::norm over the
  // channel axis of a channels-first tensor was 30x slower on CPU (a quarter of a training step).
  const auto inv_norm = (x * x).sum(1, /*keepdim=*/true).clamp_min(1e-24).rsqrt();  // [B, 1, ...]
  return x * (inv_norm * scale) * gamma;
}

ResidualBlockImpl::ResidualBlockImpl(int64_t in, int64_t out, double dropout_) : dropout(dropout_) {
  norm1 = RmsNorm(in, false);
  conv1 = CausalConv3d(in, out, std::vector<int64_t>{3, 3, 3}, std::vector<int64_t>{1, 1, 1},
                       std::vector<int64_t>{1, 1, 1});
  norm2 = RmsNorm(out, false);
  conv2 = CausalConv3d(out, out, std::vector<int64_t>{3, 3, 3}, std::vector<int64_t>{1, 1, 1},
                       std::vector<int64_t>{1, 1, 1});
  // Released Sequential: 0 norm, 1 SiLU, 2 conv, 3 norm, 4 SiLU, 5 Dropout, 6 conv.
  residual = register_module("residual",
                             torch::nn::ModuleList(norm1, torch::nn::SiLU(), conv1, norm2, torch::nn::SiLU(),
                                                   torch::nn::Dropout(dropout), conv2));
  if (in != out) shortcut = register_module("shortcut", CausalConv3d(in, out, std::vector<int64_t>{1, 1, 1}));
}

torch::Tensor ResidualBlockImpl::forward(const torch::Tensor& x, WanVaeCache* cache) {
  const auto h = shortcut ? shortcut->forward(x) : x;  // [B, out, T, H, W]
  auto y = torch::silu(norm1->forward(x));
  y = cached_conv(*conv1, y, cache);
  y = torch::silu(norm2->forward(y));
  if (dropout > 0) y = torch::dropout(y, dropout, is_training());
  y = cached_conv(*conv2, y, cache);
  return y + h;
}

AttentionBlockImpl::AttentionBlockImpl(int64_t dim) {
  norm = register_module("norm", RmsNorm(dim, true));
  to_qkv = register_module("to_qkv", torch::nn::Conv2d(torch::nn::Conv2dOptions(dim, dim * 3, 1)));
  proj = register_module("proj", torch::nn::Conv2d(torch::nn::Conv2dOptions(dim, dim, 1)));
  // Released training init zeroes proj so the block starts as identity.
  torch::NoGradGuard no_grad;
  proj->weight.zero_();
}

torch::Tensor AttentionBlockImpl::forward(const torch::Tensor& x) {
  const int64_t b = x.size(0), c = x.size(1), h = x.size(3), w = x.size(4);
  auto y = norm->forward(fold_time(x));  // [BT, C, H, W]
  auto qkv =
      to_qkv->forward(y).reshape({y.size(0), 1, 3 * c, h * w}).permute({0, 1, 3, 2});  // [BT, 1, HW, 3C]
  auto parts = qkv.chunk(3, -1);                                      // q, k, v: [BT, 1, HW, C]
  auto o = attention(parts[0], parts[1], parts[2]);                   // [BT, 1, HW, C]
  o = o.squeeze(1).permute({0, 2, 1}).reshape({y.size(0), c, h, w});  // [BT, C, H, W]
  return unfold_time(proj->forward(o), b) + x;                        // [B, C, T, H, W]
}

ResampleImpl::ResampleImpl(int64_t dim, Mode mode_) : mode(mode_) {
  const bool up = mode == Mode::kUpsample2d || mode == Mode::kUpsample3d;
  // Index 0 is parameter-free (ZeroPad2d or Upsample) in the release; 1 is the Conv2d.
  conv = up ? torch::nn::Conv2d(torch::nn::Conv2dOptions(dim, dim / 2, 3).padding(1))
            : torch::nn::Conv2d(torch::nn::Conv2dOptions(dim, dim, 3).stride(2));
  resample = register_module("resample", torch::nn::ModuleList(torch::nn::Identity(), conv));
  if (mode == Mode::kUpsample3d)
    time_conv = register_module(
        "time_conv", CausalConv3d(dim, dim * 2, std::vector<int64_t>{3, 1, 1}, std::vector<int64_t>{1, 1, 1},
                                  std::vector<int64_t>{1, 0, 0}));
  else if (mode == Mode::kDownsample3d)
    time_conv = register_module(
        "time_conv", CausalConv3d(dim, dim, std::vector<int64_t>{3, 1, 1}, std::vector<int64_t>{2, 1, 1},
                                  std::vector<int64_t>{0, 0, 0}));
}

namespace {
// time_conv output [B, 2C, t, H, W] -> [B, C, 2t, H, W]: first channel half is frame 2i.
torch::Tensor interleave_time(const torch::Tensor& y) {
  const int64_t b = y.size(0), c = y.size(1) / 2, t = y.size(2), h = y.size(3), w = y.size(4);
  return y.reshape({b, 2, c, t, h, w}).permute({0, 2, 3, 1, 4, 5}).reshape({b, c, 2 * t, h, w});
}
}  // namespace

torch::Tensor ResampleImpl::forward(const torch::Tensor& in, WanVaeCache* cache) {
  using S = WanVaeCache::State;
  torch::Tensor x = in;  // [B, C, T, H, W]
  const int64_t b = x.size(0);
  if (mode == Mode::kUpsample3d) {
    if (cache != nullptr) {
      auto& slot = cache->next();
      if (slot.state == S::kEmpty) {
        // First latent: one frame out, no temporal upsampling; mark the slot.
        slot.state = S::kRep;
      } else {
        auto cache_x = last_frames(x, kCacheT).clone();
        if (cache_x.size(2) < kCacheT && slot.state == S::kTensor)
          cache_x = torch::cat({last_frames(slot.x, 1), cache_x}, 2);
        if (cache_x.size(2) < kCacheT && slot.state == S::kRep)
          cache_x = torch::cat({torch::zeros_like(cache_x), cache_x}, 2);
        // After "Rep" the history is zeros (plain padding), not the first latent.
        x = slot.state == S::kRep ? time_conv->forward(x)
                                  : time_conv->forward(x, slot.x);  // [B, 2C, T, H, W]
        slot.state = S::kTensor;
        slot.x = cache_x;
        x = interleave_time(x);  // [B, C, 2T, H, W]
      }
    } else if (x.size(2) > 1) {
      // Whole clip: frame 0 passes through; the rest is one causal sequence with zero history.
      const auto rest = interleave_time(time_conv->forward(x.narrow(2, 1, x.size(2) - 1)));
      x = torch::cat({x.narrow(2, 0, 1), rest}, 2);  // [B, C, 1 + 2(T-1), H, W]
    }
  }

  auto y = fold_time(x);  // [BT, C, H, W]
  if (mode == Mode::kUpsample2d || mode == Mode::kUpsample3d) {
    const auto dtype = y.scalar_type();
    // Nearest x2 (at an integer factor "nearest" and the released "nearest-exact" agree); the
    // upsample kernel is several times faster than repeat_interleave's index_select, backward too.
    y = torch::upsample_nearest2d(y.to(torch::kFloat32), std::vector<int64_t>{2 * y.size(2), 2 * y.size(3)})
            .to(dtype);  // [BT, C, 2H, 2W]
  } else {
    y = torch::constant_pad_nd(y, {0, 1, 0, 1});  // right and bottom only
  }
  x = unfold_time(conv->forward(y), b);  // [B, C', T, H', W']

  if (mode == Mode::kDownsample3d) {
    if (cache != nullptr) {
      auto& slot = cache->next();
      if (slot.state == S::kEmpty) {
        slot.state = S::kTensor;
        slot.x = x.clone();  // first chunk: no temporal downsampling
      } else {
        auto cache_x = last_frames(x, 1).clone();
        x = time_conv->forward(torch::cat({last_frames(slot.x, 1), x}, 2));  // [B, C, T/2, H, W]
        slot.x = cache_x;
      }
    } else if (x.size(2) > 1) {
      // Whole clip: windows (0,1,2), (2,3,4), ... equal the chunked (last cached, next 4) ones.
      x = torch::cat({x.narrow(2, 0, 1), time_conv->forward(x)}, 2);  // [B, C, 1 + (T-1)/2, H, W]
    }
  }
  return x;
}

// --- encoder / decoder ---------------------------------------------------------------------

WanCoderImpl::WanCoderImpl(const WanVaeConfig& c, bool decoder) : is_decoder(decoder) {
  const auto& mult = c.dim_mult;
  const size_t n = mult.size();
  stages = torch::nn::ModuleList();
  auto add_block = [&](int64_t in, int64_t out, double scale) {
    stages->push_back(ResidualBlock(in, out, c.dropout));
    if (std::find(c.attn_scales.begin(), c.attn_scales.end(), scale) != c.attn_scales.end())
      stages->push_back(AttentionBlock(out));
  };
  int64_t out_dim = 0;
  if (!decoder) {
    std::vector<int64_t> dims = {c.dim};
    for (auto m : mult) dims.push_back(c.dim * m);
    conv1 =
        register_module("conv1", CausalConv3d(3, dims[0], std::vector<int64_t>{3, 3, 3},
                                              std::vector<int64_t>{1, 1, 1}, std::vector<int64_t>{1, 1, 1}));
    double scale = 1.0;
    for (size_t i = 0; i < n; ++i) {
      int64_t in = dims[i];
      out_dim = dims[i + 1];
      for (int64_t r = 0; r < c.num_res_blocks; ++r, in = out_dim) add_block(in, out_dim, scale);
      if (i != n - 1) {
        stages->push_back(Resample(out_dim, c.temperal_downsample[i] ? ResampleImpl::Mode::kDownsample3d
                                                                     : ResampleImpl::Mode::kDownsample2d));
        scale /= 2.0;
      }
    }
  } else {
    std::vector<int64_t> dims = {c.dim * mult.back()};
    for (auto it = mult.rbegin(); it != mult.rend(); ++it) dims.push_back(c.dim * *it);
    conv1 =
        register_module("conv1", CausalConv3d(c.z_dim, dims[0], std::vector<int64_t>{3, 3, 3},
                                              std::vector<int64_t>{1, 1, 1}, std::vector<int64_t>{1, 1, 1}));
    double scale = 1.0 / std::pow(2.0, static_cast<double>(n) - 2);
    for (size_t i = 0; i < n; ++i) {
      // Stages after the first take the halved width the previous upsample conv produced.
      int64_t in = (i >= 1 && i <= 3) ? dims[i] / 2 : dims[i];
      out_dim = dims[i + 1];
      for (int64_t r = 0; r < c.num_res_blocks + 1; ++r, in = out_dim) add_block(in, out_dim, scale);
      if (i != n - 1) {
        const bool temporal = c.temperal_downsample[n - 2 - i];  // reversed
        stages->push_back(
            Resample(out_dim, temporal ? ResampleImpl::Mode::kUpsample3d : ResampleImpl::Mode::kUpsample2d));
        scale *= 2.0;
      }
    }
  }
  const int64_t mid = c.dim * mult.back();
  middle = torch::nn::ModuleList(ResidualBlock(mid, mid, c.dropout), AttentionBlock(mid),
                                 ResidualBlock(mid, mid, c.dropout));
  // Released registration (= state-dict) order: encoder conv1, downsamples, middle, head;
  // decoder conv1, middle, upsamples, head.
  if (decoder) {
    register_module("middle", middle);
    register_module("upsamples", stages);
  } else {
    register_module("downsamples", stages);
    register_module("middle", middle);
  }
  head_norm = RmsNorm(out_dim, false);
  head_conv = CausalConv3d(out_dim, decoder ? 3 : c.z_dim * 2, std::vector<int64_t>{3, 3, 3},
                           std::vector<int64_t>{1, 1, 1}, std::vector<int64_t>{1, 1, 1});
  head = register_module("head", torch::nn::ModuleList(head_norm, torch::nn::SiLU(), head_conv));
}

torch::Tensor WanCoderImpl::forward(const torch::Tensor& in, WanVaeCache* cache) {
  auto x = cached_conv(*conv1, in, cache);
  auto run = [&](const std::shared_ptr<torch::nn::Module>& m) {
    if (auto r = std::dynamic_pointer_cast<ResidualBlockImpl>(m)) return r->forward(x, cache);
    if (auto a = std::dynamic_pointer_cast<AttentionBlockImpl>(m)) return a->forward(x);
    if (auto s = std::dynamic_pointer_cast<ResampleImpl>(m)) return s->forward(x, cache);
    throw Error("WanVae: unexpected module in stage list");
  };
  // The decoder runs its middle block first, at the lowest resolution.
  if (is_decoder)
    for (const auto& m : *middle) x = run(m);
  for (const auto& m : *stages) x = run(m);
  if (!is_decoder)
    for (const auto& m : *middle) x = run(m);
  x = torch::silu(head_norm->forward(x));
  return cached_conv(*head_conv, x, cache);
}

// --- top level -----------------------------------------------------------------------------

WanVaeImpl::WanVaeImpl(WanVaeConfig config) : config_(std::move(config)) {
  const int64_t z = config_.z_dim;
  encoder = register_module("encoder", WanCoder(config_, false));
  conv1 = register_module("conv1", CausalConv3d(2 * z, 2 * z, std::vector<int64_t>{1, 1, 1}));
  conv2 = register_module("conv2", CausalConv3d(z, z, std::vector<int64_t>{1, 1, 1}));
  decoder = register_module("decoder", WanCoder(config_, true));
}

torch::Tensor WanVaeImpl::encoder_forward(const torch::Tensor& x, WanVaeCache* cache) {
  return encoder->forward(x, cache);
}

torch::Tensor WanVaeImpl::decoder_forward(const torch::Tensor& x, WanVaeCache* cache) {
  return decoder->forward(x, cache);
}

torch::Tensor WanVaeImpl::encode_head(const torch::Tensor& x, bool chunked) {
  DOJO_CHECK(x.dim() == 5 && x.size(1) == 3, "WanVae::encode: expected video [B, 3, T, H, W]");
  const int64_t t = x.size(2), f = config_.spatial_factor();
  DOJO_CHECK((t - 1) % 4 == 0, "WanVae::encode: frame count " + std::to_string(t) + " is not 1 + 4k");
  DOJO_CHECK(x.size(3) % f == 0 && x.size(4) % f == 0,
             "WanVae::encode: height and width must be multiples of " + std::to_string(f));
  if (!chunked) return encoder_forward(x, nullptr);
  WanVaeCache cache;
  std::vector<torch::Tensor> outs;
  for (int64_t i = 0; i < wan_latent_frames(t); ++i) {
    cache.begin_chunk();
    const auto chunk = i == 0 ? x.narrow(2, 0, 1) : x.narrow(2, 1 + 4 * (i - 1), 4);
    outs.push_back(encoder_forward(chunk, &cache));
  }
  return torch::cat(outs, 2);  // [B, 2z, T_lat, h, w]
}

WanVaeEncoding WanVaeImpl::encode(const torch::Tensor& x, bool chunked) {
  auto parts = conv1->forward(encode_head(x, chunked)).chunk(2, 1);
  return {parts[0], parts[1]};
}

torch::Tensor WanVaeImpl::decode(const torch::Tensor& mu, bool chunked) {
  DOJO_CHECK(mu.dim() == 5 && mu.size(1) == config_.z_dim,
             "WanVae::decode: expected latents [B, z_dim, T, h, w]");
  const auto x = conv2->forward(mu);  // [B, z, T_lat, h, w]
  if (!chunked) return decoder_forward(x, nullptr);
  WanVaeCache cache;
  std::vector<torch::Tensor> outs;
  for (int64_t i = 0; i < x.size(2); ++i) {
    cache.begin_chunk();
    outs.push_back(decoder_forward(x.narrow(2, i, 1), &cache));
  }
  return torch::cat(outs, 2);  // [B, 3, 1 + 4(T_lat-1), H, W]
}

namespace {
torch::Tensor channel_vec(const std::vector<double>& v, const torch::Tensor& like) {
  return torch::tensor(v, torch::kFloat64).to(like.device(), torch::kFloat32).view({1, -1, 1, 1, 1});
}
}  // namespace

torch::Tensor WanVaeImpl::normalize(const torch::Tensor& mu) const {
  const auto inv_std = 1.0 / channel_vec(config_.latent_std, mu);  // float32 reciprocal, as released
  return ((mu - channel_vec(config_.latent_mean, mu)) * inv_std).to(mu.scalar_type());
}

torch::Tensor WanVaeImpl::denormalize(const torch::Tensor& z) const {
  const auto inv_std = 1.0 / channel_vec(config_.latent_std, z);
  return (z / inv_std + channel_vec(config_.latent_mean, z)).to(z.scalar_type());
}

// --- streaming -----------------------------------------------------------------------------

torch::Tensor WanVaeStreamEncoder::push(const torch::Tensor& frames) {
  pending_ = pending_.defined() ? torch::cat({pending_, frames}, 2) : frames;
  std::vector<torch::Tensor> outs;
  while (true) {
    const int64_t need = frames_seen_ == 0 ? 1 : 4;
    if (pending_.size(2) < need) break;
    cache_.begin_chunk();
    outs.push_back(vae_->encoder_forward(pending_.narrow(2, 0, need), &cache_));
    pending_ = pending_.narrow(2, need, pending_.size(2) - need);
    frames_seen_ += need;
  }
  if (outs.empty()) {
    const int64_t f = vae_->config().spatial_factor();
    return torch::empty({frames.size(0), vae_->config().z_dim, 0, frames.size(3) / f, frames.size(4) / f},
                        frames.options());
  }
  return vae_->conv1->forward(torch::cat(outs, 2)).chunk(2, 1)[0];  // mu [B, z, k, h, w]
}

void WanVaeStreamEncoder::reset() {
  cache_.clear();
  pending_ = torch::Tensor();
  frames_seen_ = 0;
}

torch::Tensor WanVaeStreamDecoder::push(const torch::Tensor& mu) {
  const auto x = vae_->conv2->forward(mu);  // 1x1x1: frame-wise, so per-push is exact
  std::vector<torch::Tensor> outs;
  for (int64_t i = 0; i < x.size(2); ++i) {
    cache_.begin_chunk();
    outs.push_back(vae_->decoder_forward(x.narrow(2, i, 1), &cache_));
  }
  return torch::cat(outs, 2);
}

// ---------------------------------------------------------------------------------------------
// Inputs and checkpoints

torch::Tensor video_to_model(const torch::Tensor& u8) {
  return u8.permute({0, 4, 1, 2, 3}).to(torch::kFloat32) / 127.5 - 1.0;  // [B, 3, T, H, W]
}

torch::Tensor model_to_video(const torch::Tensor& x) {
  return ((x.clamp(-1, 1) + 1) * 127.5).round().to(torch::kUInt8).permute({0, 2, 3, 4, 1}).contiguous();
}

torch::Tensor reconstruct(WanVae& vae, const torch::Tensor& video) {
  torch::NoGradGuard no_grad;
  return vae->decode(vae->encode(video).mu).clamp(-1, 1);
}

torch::Tensor reconstruct_frames(WanVae& vae, const torch::Tensor& video_u8) {
  DOJO_CHECK(video_u8.dim() == 5 && video_u8.size(4) == 3 && (video_u8.size(1) - 1) % 4 == 0,
             "reconstruct_frames: expected uint8 frames [B, 1 + 4k, H, W, 3]");
  return model_to_video(reconstruct(vae, video_to_model(video_u8)));
}

CheckpointData tokenizer_checkpoint(const WanVaeImpl& vae) {
  CheckpointData data;
  data.config = {{"model", "wan21_vae"}, {"config", vae.config().to_json()}};
  data.model = state_dict(vae);
  return data;
}

void save_tokenizer(const std::filesystem::path& dir, const WanVaeImpl& vae) {
  save_checkpoint(dir, tokenizer_checkpoint(vae));
}

WanVae load_tokenizer(const std::filesystem::path& dir) {
  const auto ck = Checkpoint::open(resolve_checkpoint_dir(dir));
  const auto& cfg = ck.config();
  DOJO_CHECK(cfg.contains("config"), (ck.dir() / "config.json").string() + ": missing field 'config'");
  WanVae vae(WanVaeConfig::from_json(cfg.at("config")));
  load_state_dict(*vae, ck.model());  // strict: a mismatch throws, naming the tensors
  vae->eval();
  return vae;
}

}  // namespace dojo::models
