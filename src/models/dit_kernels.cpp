#include "models/dit_kernels.h"

#include <ATen/Parallel.h>
#include <torch/torch.h>

#include <cmath>

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

// One row of modulate: out = (x - mean) · rstd · (1 + scale) + shift over n elements.
DOJO_AVX2_CLONES
void modulate_row(const float* __restrict x, const float* __restrict shift, const float* __restrict scale,
                  float* __restrict out, int64_t n, float eps) {
  const float mean = lane_sum(n, [&](int64_t i) { return x[i]; }) / static_cast<float>(n);
  const float squares = lane_sum(n, [&](int64_t i) { return (x[i] - mean) * (x[i] - mean); });
  const float rstd = 1.0f / std::sqrt(squares / static_cast<float>(n) + eps);
  for (int64_t i = 0; i < n; ++i) out[i] = (x[i] - mean) * rstd * (1.0f + scale[i]) + shift[i];
}

// One (token, head) row of rms_norm_rope: y = x · rsqrt(mean(x²) + eps) · w, then
// out[i] = f (y[i] cos[i] - y[i + d/2] sin[i]) for i < d/2 and f (y[i] cos[i] + y[i - d/2] sin[i])
// after (cos, sin null: out = f y).
DOJO_AVX2_CLONES
void rms_norm_rope_row(const float* __restrict x, const float* __restrict w, const float* __restrict cos,
                       const float* __restrict sin, float* __restrict out, int64_t d, float eps,
                       float factor) {
  const float squares = lane_sum(d, [&](int64_t i) { return x[i] * x[i]; });
  const float r = factor / std::sqrt(squares / static_cast<float>(d) + eps);
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

// Whole rows per task: the rows are short (D or head_dim numbers), so at least 64 of them.
constexpr int64_t kRowsPerTask = 64;

}  // namespace

namespace {
thread_local int plain_scopes = 0;
}  // namespace

PlainDitKernelsScope::PlainDitKernelsScope() { ++plain_scopes; }
PlainDitKernelsScope::~PlainDitKernelsScope() { --plain_scopes; }

bool fused_dit_kernels_apply(const torch::Tensor& x) {
  return x.is_cpu() && x.scalar_type() == torch::kFloat32 && !torch::GradMode::is_enabled() &&
         plain_scopes == 0 && !plain_kernels();
}

torch::Tensor modulate_plain(const torch::Tensor& x, const torch::Tensor& shift, const torch::Tensor& scale) {
  const auto normed = torch::layer_norm(x, {x.size(-1)}, {}, {}, 1e-6);
  return normed * (1 + scale) + shift;
}

torch::Tensor modulate_fused(const torch::Tensor& input, const torch::Tensor& shift_in,
                             const torch::Tensor& scale_in) {
  DOJO_CHECK(input.dim() == 4, "modulate: x must be [B, T, S, D]");
  const auto x = input.contiguous();
  const int64_t B = x.size(0), T = x.size(1), S = x.size(2), D = x.size(3);
  // [B, T, 1, D] views whose size-1 dims have stride 0; rows of D contiguous numbers.
  auto rows_of = [&](const torch::Tensor& t) {
    auto e = t.expand({B, T, 1, D});
    return e.stride(3) == 1 ? e : e.contiguous();
  };
  const auto shift = rows_of(shift_in), scale = rows_of(scale_in);
  auto out = torch::empty_like(x);
  const float* xp = x.data_ptr<float>();
  const float* sp = shift.data_ptr<float>();
  const float* cp = scale.data_ptr<float>();
  float* op = out.data_ptr<float>();
  const int64_t shift_b = shift.stride(0), shift_t = shift.stride(1);
  const int64_t scale_b = scale.stride(0), scale_t = scale.stride(1);
  at::parallel_for(0, B * T * S, kRowsPerTask, [&](int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; ++r) {
      const int64_t b = r / (T * S), t = (r / S) % T;
      modulate_row(xp + r * D, sp + b * shift_b + t * shift_t, cp + b * scale_b + t * scale_t, op + r * D, D,
                   1e-6f);
    }
  });
  return out;
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
  DOJO_CHECK(input.dim() == 4, "rms_norm_rope: x must be [B, L, h, d]");
  const auto x = input.contiguous();
  const int64_t B = x.size(0), L = x.size(1), H = x.size(2), d = x.size(3);
  DOJO_CHECK(d % 2 == 0 && weight_in.numel() == d, "rms_norm_rope: the weight must have head_dim numbers");
  const auto weight = weight_in.to(torch::kFloat32).contiguous();
  torch::Tensor cos, sin;
  if (cos_in.defined()) {
    DOJO_CHECK(sin_in.defined() && cos_in.numel() == L * d && sin_in.numel() == L * d,
               "rms_norm_rope: cos and sin must be [L, 1, head_dim] for the tokens of x");
    cos = cos_in.to(torch::kFloat32).contiguous();
    sin = sin_in.to(torch::kFloat32).contiguous();
  }
  auto out = torch::empty_like(x);
  const float* xp = x.data_ptr<float>();
  const float* wp = weight.data_ptr<float>();
  const float* cp = cos.defined() ? cos.data_ptr<float>() : nullptr;
  const float* sp = sin.defined() ? sin.data_ptr<float>() : nullptr;
  float* op = out.data_ptr<float>();
  at::parallel_for(0, B * L * H, kRowsPerTask, [&](int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; ++r) {
      const int64_t l = (r / H) % L;
      rms_norm_rope_row(xp + r * d, wp, cp != nullptr ? cp + l * d : nullptr,
                        sp != nullptr ? sp + l * d : nullptr, op + r * d, d, static_cast<float>(eps),
                        static_cast<float>(factor));
    }
  });
  return out;
}

}  // namespace dojo::models
