#include "models/dit_kernels.h"

#include <ATen/Parallel.h>
#include <torch/torch.h>

#include <cmath>

#include "core/autocast.h"
#include "core/error.h"
#include "core/runtime.h"

namespace dojo::models {
namespace {

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define DOJO_AVX2_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define DOJO_AVX2_CLONES
#endif

// Sums in 8 independent lanes, so the compiler can vectorise them without reassociating a single
// running sum (which it may not do under IEEE rules). n need not be a multiple of 8.
template <class F>
inline __attribute__((always_inline)) float lane_sum(int64_t n, F&& term) {
  float lanes[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  int64_t i = 0;
  for (; i + 8 <= n; i += 8)
    for (int j = 0; j < 8; ++j) lanes[j] += term(i + j);
  for (; i < n; ++i) lanes[0] += term(i);
  return ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3])) + ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7]));
}

// One row of modulate: out = (x - mean) · rstd · (1 + scale) + shift over n elements; the row's
// mean and rstd go to `stats` when the backward pass will need them.
DOJO_AVX2_CLONES
void modulate_row(const float* __restrict x, const float* __restrict shift, const float* __restrict scale,
                  float* __restrict out, int64_t n, float eps, float* __restrict stats) {
  const float mean = lane_sum(n, [&](int64_t i) { return x[i]; }) / static_cast<float>(n);
  const float squares = lane_sum(n, [&](int64_t i) { return (x[i] - mean) * (x[i] - mean); });
  const float rstd = 1.0f / std::sqrt(squares / static_cast<float>(n) + eps);
  for (int64_t i = 0; i < n; ++i) out[i] = (x[i] - mean) * rstd * (1.0f + scale[i]) + shift[i];
  if (stats != nullptr) {
    stats[0] = mean;
    stats[1] = rstd;
  }
}

// The gradient of one modulate row. With x̂ = (x - mean) · rstd and h = g · (1 + scale):
// dx = rstd · (h - mean(h) - x̂ · mean(h · x̂)) (LayerNorm's backward); the row adds g to the
// shift's gradient and g · x̂ to the scale's.
DOJO_AVX2_CLONES
void modulate_row_backward(const float* __restrict x, const float* __restrict g,
                           const float* __restrict scale, float mean, float rstd, float* __restrict dx,
                           float* __restrict d_shift, float* __restrict d_scale, int64_t n) {
  const float inv_n = 1.0f / static_cast<float>(n);
  const float h_mean = lane_sum(n, [&](int64_t i) { return g[i] * (1.0f + scale[i]); }) * inv_n;
  const float hx_mean =
      lane_sum(n, [&](int64_t i) { return g[i] * (1.0f + scale[i]) * ((x[i] - mean) * rstd); }) * inv_n;
  for (int64_t i = 0; i < n; ++i) {
    const float x_hat = (x[i] - mean) * rstd;
    dx[i] = rstd * (g[i] * (1.0f + scale[i]) - h_mean - x_hat * hx_mean);
    d_shift[i] += g[i];
    d_scale[i] += g[i] * x_hat;
  }
}

// One (token, head) row of rms_norm_rope: y = x · rsqrt(mean(x²) + eps) · w, then
// out[i] = f (y[i] cos[i] - y[i + d/2] sin[i]) for i < d/2 and f (y[i] cos[i] + y[i - d/2] sin[i])
// after (cos, sin null: out = f y).
// `rms`, when given, receives rsqrt(mean(x²) + eps) for the backward pass.
DOJO_AVX2_CLONES
void rms_norm_rope_row(const float* __restrict x, const float* __restrict w, const float* __restrict cos,
                       const float* __restrict sin, float* __restrict out, int64_t d, float eps, float factor,
                       float* __restrict rms) {
  const float squares = lane_sum(d, [&](int64_t i) { return x[i] * x[i]; });
  const float inv_rms = 1.0f / std::sqrt(squares / static_cast<float>(d) + eps);
  if (rms != nullptr) *rms = inv_rms;
  const float r = factor * inv_rms;
  if (cos == nullptr) {
    for (int64_t i = 0; i < d; ++i) out[i] = x[i] * r * w[i];
    return;
  }
  const int64_t half = d / 2;
  for (int64_t i = 0; i < half; ++i) {
    const float a = x[i] * w[i], b = x[i + half] * w[i + half];
    out[i] = r * (a * cos[i] - b * sin[i]);
    out[i + half] = r * (b * cos[i + half] + a * sin[i + half]);
  }
}

// The gradient of one rms_norm_rope row, with r = rsqrt(mean(x²) + eps) from the forward pass:
// first the rotation undone (dy = f Rᵀ g), then with u = dy · w: dx = r u - x r³ mean(u · x), and
// the row adds dy · x · r to the weight's gradient. `dy` is scratch of d numbers.
DOJO_AVX2_CLONES
void rms_norm_rope_row_backward(const float* __restrict x, const float* __restrict w,
                                const float* __restrict cos, const float* __restrict sin,
                                const float* __restrict g, float r, float factor, float* __restrict dx,
                                float* __restrict d_weight, float* __restrict dy, int64_t d) {
  if (cos == nullptr) {
    for (int64_t i = 0; i < d; ++i) dy[i] = factor * g[i];
  } else {
    const int64_t half = d / 2;
    for (int64_t i = 0; i < half; ++i) {
      dy[i] = factor * (g[i] * cos[i] + g[i + half] * sin[i + half]);
      dy[i + half] = factor * (g[i + half] * cos[i + half] - g[i] * sin[i]);
    }
  }
  const float ux_mean = lane_sum(d, [&](int64_t i) { return dy[i] * w[i] * x[i]; }) / static_cast<float>(d);
  for (int64_t i = 0; i < d; ++i) {
    dx[i] = r * dy[i] * w[i] - x[i] * r * r * r * ux_mean;
    d_weight[i] += dy[i] * x[i] * r;
  }
}

// One row of the gated residual, out = x + gate · r, and its backward: dr = g · gate, and the row
// adds g · r to the gate's gradient (dx is g itself).
DOJO_AVX2_CLONES
void gated_residual_row(const float* __restrict x, const float* __restrict gate, const float* __restrict r,
                        float* __restrict out, int64_t n) {
  for (int64_t i = 0; i < n; ++i) out[i] = x[i] + gate[i] * r[i];
}

DOJO_AVX2_CLONES
void gated_residual_row_backward(const float* __restrict g, const float* __restrict gate,
                                 const float* __restrict r, float* __restrict dr, float* __restrict d_gate,
                                 int64_t n) {
  for (int64_t i = 0; i < n; ++i) {
    dr[i] = g[i] * gate[i];
    d_gate[i] += g[i] * r[i];
  }
}

// Whole rows per task: the rows are short (D or head_dim numbers), so at least 64 of them.
constexpr int64_t kRowsPerTask = 64;

}  // namespace

namespace {
thread_local int plain_scopes = 0;
}  // namespace

PlainDitKernelsScope::PlainDitKernelsScope() { ++plain_scopes; }
PlainDitKernelsScope::~PlainDitKernelsScope() { --plain_scopes; }

bool fused_dit_kernels_apply(std::initializer_list<torch::Tensor> inputs) {
  if (inputs.size() == 0 || plain_scopes > 0 || plain_kernels()) return false;
  for (const auto& t : inputs)
    if (!t.is_cpu() || t.scalar_type() != torch::kFloat32) return false;
  // Training under bf16 autocast keeps libtorch's operators: the fused backward passes are for
  // float32 training (under autocast their float32 sums, cast to bf16 on the way back, differ from
  // the plain path's by a bf16 rounding here and there).
  return !(torch::GradMode::is_enabled() && AutocastGuard::is_enabled(c10::DeviceType::CPU));
}

torch::Tensor modulate_plain(const torch::Tensor& x, const torch::Tensor& shift, const torch::Tensor& scale) {
  const auto normed = torch::layer_norm(x, {x.size(-1)}, {}, {}, 1e-6);
  return normed * (1 + scale) + shift;
}

namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

// [B, T, 1, D] views of a shift or scale whose size-1 dims have stride 0; rows of D contiguous
// numbers.
torch::Tensor modulation_rows(const torch::Tensor& t, int64_t B, int64_t T, int64_t D) {
  auto e = t.expand({B, T, 1, D});
  return e.stride(3) == 1 ? e : e.contiguous();
}

// x contiguous [B, T, S, D]; `stats` [B·T·S, 2] (mean, rstd per row) or undefined.
torch::Tensor modulate_rows(const torch::Tensor& x, const torch::Tensor& shift_in,
                            const torch::Tensor& scale_in, const torch::Tensor& stats) {
  const int64_t B = x.size(0), T = x.size(1), S = x.size(2), D = x.size(3);
  const auto shift = modulation_rows(shift_in, B, T, D), scale = modulation_rows(scale_in, B, T, D);
  auto out = torch::empty_like(x);
  const float* xp = x.data_ptr<float>();
  const float* sp = shift.data_ptr<float>();
  const float* cp = scale.data_ptr<float>();
  float* op = out.data_ptr<float>();
  float* statp = stats.defined() ? stats.data_ptr<float>() : nullptr;
  const int64_t shift_b = shift.stride(0), shift_t = shift.stride(1);
  const int64_t scale_b = scale.stride(0), scale_t = scale.stride(1);
  at::parallel_for(0, B * T * S, kRowsPerTask, [&](int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; ++r) {
      const int64_t b = r / (T * S), t = (r / S) % T;
      modulate_row(xp + r * D, sp + b * shift_b + t * shift_t, cp + b * scale_b + t * scale_t, op + r * D, D,
                   1e-6f, statp != nullptr ? statp + 2 * r : nullptr);
    }
  });
  return out;
}

// modulate with its own backward pass: one pass over the rows each way, where libtorch records
// LayerNorm, two multiplies and two adds, and runs their backward operators plus the reductions
// of the broadcast shift and scale.
struct ModulateFunction : torch::autograd::Function<ModulateFunction> {
  static torch::Tensor forward(AutogradContext* ctx, const torch::Tensor& input, const torch::Tensor& shift,
                               const torch::Tensor& scale) {
    const auto x = input.contiguous();
    const auto stats = torch::empty({x.size(0) * x.size(1) * x.size(2), 2}, x.options());
    auto out = modulate_rows(x, shift, scale, stats);
    ctx->save_for_backward({x, scale, stats});
    ctx->saved_data["shift_sizes"] = shift.sizes().vec();
    return out;
  }

  static variable_list backward(AutogradContext* ctx, variable_list grad_outputs) {
    const auto saved = ctx->get_saved_variables();
    const auto &x = saved[0], &scale_in = saved[1], &stats = saved[2];
    const auto g = grad_outputs[0].contiguous();
    const int64_t B = x.size(0), T = x.size(1), S = x.size(2), D = x.size(3);
    const auto scale = modulation_rows(scale_in, B, T, D);
    auto dx = torch::empty_like(x);
    auto d_shift = torch::zeros({B, T, 1, D}, x.options()), d_scale = torch::zeros({B, T, 1, D}, x.options());
    const float* xp = x.data_ptr<float>();
    const float* gp = g.data_ptr<float>();
    const float* cp = scale.data_ptr<float>();
    const float* statp = stats.data_ptr<float>();
    float* dxp = dx.data_ptr<float>();
    float* dsp = d_shift.data_ptr<float>();
    float* dcp = d_scale.data_ptr<float>();
    const int64_t scale_b = scale.stride(0), scale_t = scale.stride(1);
    // One task per (clip, frame): its S rows add into the same shift and scale gradients.
    at::parallel_for(0, B * T, 1, [&](int64_t begin, int64_t end) {
      for (int64_t bt = begin; bt < end; ++bt) {
        const float* scale_row = cp + (bt / T) * scale_b + (bt % T) * scale_t;
        for (int64_t s = 0; s < S; ++s) {
          const int64_t r = bt * S + s;
          modulate_row_backward(xp + r * D, gp + r * D, scale_row, statp[2 * r], statp[2 * r + 1],
                                dxp + r * D, dsp + bt * D, dcp + bt * D, D);
        }
      }
    });
    const auto shift_sizes = ctx->saved_data["shift_sizes"].toIntVector();
    return {dx, d_shift.sum_to_size(shift_sizes), d_scale.sum_to_size(scale_in.sizes())};
  }
};

// x contiguous [B, L, h, d]; weight float32 [d]; cos and sin float32 [L·d] or empty; `rms` [B·L·h]
// or undefined.
torch::Tensor rms_norm_rope_rows(const torch::Tensor& x, const torch::Tensor& weight, double eps,
                                 const torch::Tensor& cos, const torch::Tensor& sin, double factor,
                                 const torch::Tensor& rms) {
  const int64_t B = x.size(0), L = x.size(1), H = x.size(2), d = x.size(3);
  auto out = torch::empty_like(x);
  const float* xp = x.data_ptr<float>();
  const float* wp = weight.data_ptr<float>();
  const bool rotate = cos.numel() > 0;
  const float* cp = rotate ? cos.data_ptr<float>() : nullptr;
  const float* sp = rotate ? sin.data_ptr<float>() : nullptr;
  float* op = out.data_ptr<float>();
  float* rp = rms.defined() ? rms.data_ptr<float>() : nullptr;
  at::parallel_for(0, B * L * H, kRowsPerTask, [&](int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; ++r) {
      const int64_t l = (r / H) % L;
      rms_norm_rope_row(xp + r * d, wp, rotate ? cp + l * d : nullptr, rotate ? sp + l * d : nullptr,
                        op + r * d, d, static_cast<float>(eps), static_cast<float>(factor),
                        rp != nullptr ? rp + r : nullptr);
    }
  });
  return out;
}

// rms_norm_rope with its own backward pass (the plain path records about 12 operators and runs
// twice as many backward). cos and sin are constants: empty tensors stand for "no rotation"
// (libtorch 1.13 refuses undefined tensors among a Function's inputs).
struct RmsNormRopeFunction : torch::autograd::Function<RmsNormRopeFunction> {
  static torch::Tensor forward(AutogradContext* ctx, const torch::Tensor& input, const torch::Tensor& weight,
                               const torch::Tensor& cos, const torch::Tensor& sin, double eps,
                               double factor) {
    const auto x = input.contiguous();
    const auto w = weight.contiguous();
    const auto rms = torch::empty({x.size(0) * x.size(1) * x.size(2)}, x.options());
    auto out = rms_norm_rope_rows(x, w, eps, cos, sin, factor, rms);
    ctx->save_for_backward({x, w, cos, sin, rms});
    ctx->saved_data["factor"] = factor;
    return out;
  }

  static variable_list backward(AutogradContext* ctx, variable_list grad_outputs) {
    const auto saved = ctx->get_saved_variables();
    const auto &x = saved[0], &w = saved[1], &cos = saved[2], &sin = saved[3], &rms = saved[4];
    const auto g = grad_outputs[0].contiguous();
    const auto factor = static_cast<float>(ctx->saved_data["factor"].toDouble());
    const int64_t B = x.size(0), L = x.size(1), H = x.size(2), d = x.size(3);
    const bool rotate = cos.numel() > 0;
    auto dx = torch::empty_like(x);
    const float* xp = x.data_ptr<float>();
    const float* wp = w.data_ptr<float>();
    const float* cp = rotate ? cos.data_ptr<float>() : nullptr;
    const float* sp = rotate ? sin.data_ptr<float>() : nullptr;
    const float* gp = g.data_ptr<float>();
    const float* rp = rms.data_ptr<float>();
    float* dxp = dx.data_ptr<float>();
    // The weight's gradient sums over every row: each block of rows sums into a slot of its own,
    // and the slots are added in order, so the result does not depend on the thread count.
    const int64_t rows = B * L * H, blocks = (rows + kRowsPerTask - 1) / kRowsPerTask;
    auto partial = torch::zeros({blocks, 2 * d}, x.options());  // per block: its sum, then dy scratch
    float* pp = partial.data_ptr<float>();
    at::parallel_for(0, blocks, 1, [&](int64_t first, int64_t last) {
      for (int64_t block = first; block < last; ++block) {
        float* sum = pp + block * 2 * d;
        for (int64_t r = block * kRowsPerTask; r < std::min(rows, (block + 1) * kRowsPerTask); ++r) {
          const int64_t l = (r / H) % L;
          rms_norm_rope_row_backward(xp + r * d, wp, rotate ? cp + l * d : nullptr,
                                     rotate ? sp + l * d : nullptr, gp + r * d, rp[r], factor, dxp + r * d,
                                     sum, sum + d, d);
        }
      }
    });
    auto d_weight = torch::zeros({d}, x.options());
    float* dw = d_weight.data_ptr<float>();
    for (int64_t block = 0; block < blocks; ++block)
      for (int64_t i = 0; i < d; ++i) dw[i] += pp[block * 2 * d + i];
    return {dx, d_weight, torch::Tensor(), torch::Tensor(), torch::Tensor(), torch::Tensor()};
  }
};

// x and r contiguous [B, T, S, D]; gate rows [B, T, 1, D].
torch::Tensor gated_residual_rows(const torch::Tensor& x, const torch::Tensor& gate_in,
                                  const torch::Tensor& r) {
  const int64_t B = x.size(0), T = x.size(1), S = x.size(2), D = x.size(3);
  const auto gate = modulation_rows(gate_in, B, T, D);
  auto out = torch::empty_like(x);
  const float* xp = x.data_ptr<float>();
  const float* gp = gate.data_ptr<float>();
  const float* rp = r.data_ptr<float>();
  float* op = out.data_ptr<float>();
  const int64_t gate_b = gate.stride(0), gate_t = gate.stride(1);
  at::parallel_for(0, B * T * S, kRowsPerTask, [&](int64_t begin, int64_t end) {
    for (int64_t row = begin; row < end; ++row) {
      const int64_t b = row / (T * S), t = (row / S) % T;
      gated_residual_row(xp + row * D, gp + b * gate_b + t * gate_t, rp + row * D, op + row * D, D);
    }
  });
  return out;
}

// x + gate · r with its own backward pass (libtorch: a multiply and an add forward; backward the
// multiply's two products and the reduction of the broadcast gate).
struct GatedResidualFunction : torch::autograd::Function<GatedResidualFunction> {
  static torch::Tensor forward(AutogradContext* ctx, const torch::Tensor& x, const torch::Tensor& gate,
                               const torch::Tensor& r_in) {
    const auto r = r_in.contiguous();
    ctx->save_for_backward({gate, r});
    return gated_residual_rows(x.contiguous(), gate, r);
  }

  static variable_list backward(AutogradContext* ctx, variable_list grad_outputs) {
    const auto saved = ctx->get_saved_variables();
    const auto &gate_in = saved[0], &r = saved[1];
    const auto g = grad_outputs[0].contiguous();
    const int64_t B = r.size(0), T = r.size(1), S = r.size(2), D = r.size(3);
    const auto gate = modulation_rows(gate_in, B, T, D);
    auto dr = torch::empty_like(r);
    auto d_gate = torch::zeros({B, T, 1, D}, r.options());
    const float* gp = g.data_ptr<float>();
    const float* gatep = gate.data_ptr<float>();
    const float* rp = r.data_ptr<float>();
    float* drp = dr.data_ptr<float>();
    float* dgp = d_gate.data_ptr<float>();
    const int64_t gate_b = gate.stride(0), gate_t = gate.stride(1);
    // One task per (clip, frame): its S rows add into the same gate gradient.
    at::parallel_for(0, B * T, 1, [&](int64_t begin, int64_t end) {
      for (int64_t bt = begin; bt < end; ++bt) {
        const float* gate_row = gatep + (bt / T) * gate_b + (bt % T) * gate_t;
        for (int64_t s = 0; s < S; ++s) {
          const int64_t row = bt * S + s;
          gated_residual_row_backward(gp + row * D, gate_row, rp + row * D, drp + row * D, dgp + bt * D, D);
        }
      }
    });
    return {g, d_gate.sum_to_size(gate_in.sizes()), dr};
  }
};

bool records_gradient(std::initializer_list<torch::Tensor> inputs) {
  if (!torch::GradMode::is_enabled()) return false;
  for (const auto& t : inputs)
    if (t.defined() && t.requires_grad()) return true;
  return false;
}

}  // namespace

torch::Tensor modulate_fused(const torch::Tensor& input, const torch::Tensor& shift,
                             const torch::Tensor& scale) {
  DOJO_CHECK(input.dim() == 4, "modulate: x must be [B, T, S, D]");
  DOJO_CHECK(input.scalar_type() == torch::kFloat32 && shift.scalar_type() == torch::kFloat32 &&
                 scale.scalar_type() == torch::kFloat32,
             "modulate: the fused kernel takes float32 x, shift and scale");
  if (records_gradient({input, shift, scale})) return ModulateFunction::apply(input, shift, scale);
  return modulate_rows(input.contiguous(), shift, scale, torch::Tensor());
}

torch::Tensor gated_residual_plain(const torch::Tensor& x, const torch::Tensor& gate,
                                   const torch::Tensor& r) {
  return x + gate * r;
}

torch::Tensor gated_residual_fused(const torch::Tensor& x, const torch::Tensor& gate,
                                   const torch::Tensor& r) {
  DOJO_CHECK(x.dim() == 4 && x.sizes() == r.sizes(), "gated_residual: x and r must both be [B, T, S, D]");
  DOJO_CHECK(x.scalar_type() == torch::kFloat32 && gate.scalar_type() == torch::kFloat32 &&
                 r.scalar_type() == torch::kFloat32,
             "gated_residual: the fused kernel takes float32 x, gate and r");
  if (records_gradient({x, gate, r})) return GatedResidualFunction::apply(x, gate, r);
  return gated_residual_rows(x.contiguous(), gate, r.contiguous());
}

torch::Tensor rms_norm_rope_plain(const torch::Tensor& x, const torch::Tensor& weight, double eps,
                                  const torch::Tensor& cos, const torch::Tensor& sin, double factor) {
  const auto xf = x.to(torch::kFloat32);
  auto y = (xf * torch::rsqrt(xf.pow(2).mean(-1, /*keepdim=*/true) + eps) * weight.to(torch::kFloat32));
  if (cos.defined()) {
    const int64_t half = y.size(-1) / 2;
    const auto rotated = torch::cat({-y.slice(-1, half), y.slice(-1, 0, half)}, -1);
    y = y * cos + rotated * sin;
  }
  if (factor != 1.0) y = y * factor;
  return y.to(x.scalar_type());
}

torch::Tensor rms_norm_rope_fused(const torch::Tensor& input, const torch::Tensor& weight_in, double eps,
                                  const torch::Tensor& cos_in, const torch::Tensor& sin_in, double factor) {
  DOJO_CHECK(input.dim() == 4 && input.scalar_type() == torch::kFloat32,
             "rms_norm_rope: x must be float32 [B, L, h, d]");
  const int64_t L = input.size(1), d = input.size(3);
  DOJO_CHECK(d % 2 == 0 && weight_in.numel() == d, "rms_norm_rope: the weight must have head_dim numbers");
  const auto weight = weight_in.to(torch::kFloat32);
  auto cos = torch::empty({0}, input.options()), sin = cos;
  if (cos_in.defined()) {
    DOJO_CHECK(sin_in.defined() && cos_in.numel() == L * d && sin_in.numel() == L * d,
               "rms_norm_rope: cos and sin must be [L, 1, head_dim] for the tokens of x");
    cos = cos_in.detach().to(torch::kFloat32).contiguous();
    sin = sin_in.detach().to(torch::kFloat32).contiguous();
  }
  if (records_gradient({input, weight}))
    return RmsNormRopeFunction::apply(input, weight, cos, sin, eps, factor);
  return rms_norm_rope_rows(input.contiguous(), weight.contiguous(), eps, cos, sin, factor, torch::Tensor());
}

}  // namespace dojo::models
