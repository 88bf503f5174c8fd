#include "models/lam_kernels.h"

#include <ATen/Parallel.h>
#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <utility>
#include <vector>

#include "core/error.h"

namespace dojo::models {
namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

// Where one (g, r, head) group's numbers lie in qkv [G, L, R, 3E] and in out [G, L, R, E].
struct Layout {
  int64_t L, R, E, D;
  int64_t qkv_row(int64_t g, int64_t l, int64_t r) const { return ((g * L + l) * R + r) * 3 * E; }
  int64_t out_row(int64_t g, int64_t l, int64_t r) const { return ((g * L + l) * R + r) * E; }
};

// Rotates the L rows of one head (D numbers each, interleaved pairs) in place by position:
// (x0, x1) -> (x0 c - x1 s, x1 c + x0 s), c and s of angle l · freq_j; `inverse` applies the
// transpose (the backward pass's rotation of a gradient).
void rotate_rows(float* rows, int64_t L, int64_t D, const float* cos, const float* sin, bool inverse) {
  const int64_t half = D / 2;
  for (int64_t l = 0; l < L; ++l) {
    float* x = rows + l * D;
    const float* c = cos + l * half;
    const float* s = sin + l * half;
    for (int64_t j = 0; j < half; ++j) {
      const float a = x[2 * j], b = x[2 * j + 1];
      const float sj = inverse ? -s[j] : s[j];
      x[2 * j] = a * c[j] - b * sj;
      x[2 * j + 1] = b * c[j] + a * sj;
    }
  }
}

// Copies one head's L rows of q (part 0), k (1) or v (2) out of qkv into `rows` [L, D].
void gather_head(const float* qkv, const Layout& s, int64_t g, int64_t r, int64_t head, int part,
                 float* rows) {
  for (int64_t l = 0; l < s.L; ++l) {
    const float* src = qkv + s.qkv_row(g, l, r) + part * s.E + head * s.D;
    std::copy(src, src + s.D, rows + l * s.D);
  }
}

float dot(const float* a, const float* b, int64_t n) {
  float sum = 0;
  for (int64_t i = 0; i < n; ++i) sum += a[i] * b[i];
  return sum;
}

struct Tables {
  torch::Tensor cos, sin;  // [L, D / 2] float32, empty without rotation
  const float* cos_data() const { return cos.numel() > 0 ? cos.data_ptr<float>() : nullptr; }
  const float* sin_data() const { return sin.numel() > 0 ? sin.data_ptr<float>() : nullptr; }
};

// The angles as LamRotaryImpl::rotate computes them (float32 positions times float32 frequencies,
// libtorch's cos and sin), so that both paths rotate by the same numbers.
Tables rotary_tables(const torch::Tensor& freqs, int64_t L) {
  Tables t;
  if (!freqs.defined() || freqs.numel() == 0) {
    t.cos = t.sin = torch::empty({0}, torch::kFloat32);
    return t;
  }
  const auto angles = torch::arange(L, torch::kFloat32).unsqueeze(1) * freqs.to(torch::kFloat32).unsqueeze(0);
  t.cos = angles.cos().contiguous();
  t.sin = angles.sin().contiguous();
  return t;
}

// One group's q and k (rotated) and v, each [L, D].
void load_group(const float* qkv, const Layout& s, int64_t g, int64_t r, int64_t head, const Tables& tables,
                float* q, float* k, float* v) {
  gather_head(qkv, s, g, r, head, 0, q);
  gather_head(qkv, s, g, r, head, 1, k);
  gather_head(qkv, s, g, r, head, 2, v);
  if (const float* cos = tables.cos_data()) {
    rotate_rows(q, s.L, s.D, cos, tables.sin_data(), false);
    rotate_rows(k, s.L, s.D, cos, tables.sin_data(), false);
  }
}

// Forward over every group: out [G, L, R, E]; probs [G, R, heads, L, L] kept for the backward.
void short_attention_rows(const torch::Tensor& qkv, const Tables& tables, int64_t heads, float scale,
                          torch::Tensor& out, torch::Tensor& probs) {
  const int64_t G = qkv.size(0), L = qkv.size(1), R = qkv.size(2), E = qkv.size(3) / 3;
  const Layout s{L, R, E, E / heads};
  const float* in = qkv.data_ptr<float>();
  float* o = out.data_ptr<float>();
  float* p = probs.data_ptr<float>();
  at::parallel_for(0, G * R * heads, 64, [&](int64_t begin, int64_t end) {
    std::vector<float> q(L * s.D), k(L * s.D), v(L * s.D);
    for (int64_t group = begin; group < end; ++group) {
      const int64_t head = group % heads, r = (group / heads) % R, g = group / (heads * R);
      load_group(in, s, g, r, head, tables, q.data(), k.data(), v.data());
      float* pg = p + group * L * L;  // [L, L]
      for (int64_t l = 0; l < L; ++l) {
        float* row = pg + l * L;
        float top = -INFINITY;
        for (int64_t m = 0; m < L; ++m) {
          row[m] = dot(q.data() + l * s.D, k.data() + m * s.D, s.D) * scale;
          top = std::max(top, row[m]);
        }
        float total = 0;
        for (int64_t m = 0; m < L; ++m) total += row[m] = std::exp(row[m] - top);
        for (int64_t m = 0; m < L; ++m) row[m] /= total;
        float* dst = o + s.out_row(g, l, r) + head * s.D;
        std::fill(dst, dst + s.D, 0.0f);
        for (int64_t m = 0; m < L; ++m)
          for (int64_t d = 0; d < s.D; ++d) dst[d] += row[m] * v[m * s.D + d];
      }
    }
  });
}

// The gradient of qkv from that of out. With P the probabilities and q, k rotated:
// dv = Pᵀ dO; dP = dO vᵀ; dS = P ⊙ (dP - rowsum(P ⊙ dP)) · scale; dq = dS k; dk = dSᵀ q; then
// dq and dk rotated back.
torch::Tensor short_attention_backward(const torch::Tensor& qkv, const torch::Tensor& probs,
                                       const torch::Tensor& grad_out, const Tables& tables, int64_t heads,
                                       float scale) {
  const int64_t G = qkv.size(0), L = qkv.size(1), R = qkv.size(2), E = qkv.size(3) / 3;
  const Layout s{L, R, E, E / heads};
  auto grad = torch::empty_like(qkv);
  const float* in = qkv.data_ptr<float>();
  const float* p = probs.data_ptr<float>();
  const float* go = grad_out.data_ptr<float>();
  float* gq = grad.data_ptr<float>();
  const float* cos = tables.cos_data();
  const float* sin = tables.sin_data();
  at::parallel_for(0, G * R * heads, 64, [&](int64_t begin, int64_t end) {
    std::vector<float> q(L * s.D), k(L * s.D), v(L * s.D), dO(L * s.D), dq(L * s.D), dk(L * s.D), dv(L * s.D),
        dS(L * L);
    for (int64_t group = begin; group < end; ++group) {
      const int64_t head = group % heads, r = (group / heads) % R, g = group / (heads * R);
      load_group(in, s, g, r, head, tables, q.data(), k.data(), v.data());
      for (int64_t l = 0; l < L; ++l) {
        const float* src = go + s.out_row(g, l, r) + head * s.D;
        std::copy(src, src + s.D, dO.data() + l * s.D);
      }
      const float* pg = p + group * L * L;
      std::fill(dv.begin(), dv.end(), 0.0f);
      for (int64_t l = 0; l < L; ++l) {
        float weighted = 0;
        for (int64_t m = 0; m < L; ++m) {
          const float pm = pg[l * L + m];
          dS[l * L + m] = dot(dO.data() + l * s.D, v.data() + m * s.D, s.D);  // dP
          weighted += pm * dS[l * L + m];
          for (int64_t d = 0; d < s.D; ++d) dv[m * s.D + d] += pm * dO[l * s.D + d];
        }
        for (int64_t m = 0; m < L; ++m) dS[l * L + m] = pg[l * L + m] * (dS[l * L + m] - weighted) * scale;
      }
      std::fill(dq.begin(), dq.end(), 0.0f);
      std::fill(dk.begin(), dk.end(), 0.0f);
      for (int64_t l = 0; l < L; ++l)
        for (int64_t m = 0; m < L; ++m) {
          const float w = dS[l * L + m];
          for (int64_t d = 0; d < s.D; ++d) {
            dq[l * s.D + d] += w * k[m * s.D + d];
            dk[m * s.D + d] += w * q[l * s.D + d];
          }
        }
      if (cos != nullptr) {
        rotate_rows(dq.data(), L, s.D, cos, sin, true);
        rotate_rows(dk.data(), L, s.D, cos, sin, true);
      }
      for (int64_t l = 0; l < L; ++l) {
        float* dst = gq + s.qkv_row(g, l, r) + head * s.D;
        std::copy(dq.data() + l * s.D, dq.data() + (l + 1) * s.D, dst);
        std::copy(dk.data() + l * s.D, dk.data() + (l + 1) * s.D, dst + E);
        std::copy(dv.data() + l * s.D, dv.data() + (l + 1) * s.D, dst + 2 * E);
      }
    }
  });
  return grad;
}

// qkv contiguous -> {out [G, L, R, E], probs [G, R, heads, L, L]}.
std::pair<torch::Tensor, torch::Tensor> short_attention_forward(const torch::Tensor& qkv,
                                                                const torch::Tensor& freqs, int64_t heads,
                                                                double scale) {
  const int64_t G = qkv.size(0), L = qkv.size(1), R = qkv.size(2), E = qkv.size(3) / 3;
  auto out = torch::empty({G, L, R, E}, qkv.options());
  auto probs = torch::empty({G, R, heads, L, L}, qkv.options());
  short_attention_rows(qkv, rotary_tables(freqs, L), heads, static_cast<float>(scale), out, probs);
  return {out, probs};
}

struct ShortAttentionFunction : torch::autograd::Function<ShortAttentionFunction> {
  static torch::Tensor forward(AutogradContext* ctx, const torch::Tensor& qkv_in, const torch::Tensor& freqs,
                               int64_t heads, double scale) {
    const auto qkv = qkv_in.contiguous();
    auto [out, probs] = short_attention_forward(qkv, freqs, heads, scale);
    ctx->save_for_backward({qkv, probs, freqs});
    ctx->saved_data["heads"] = heads;
    ctx->saved_data["scale"] = scale;
    return out;
  }

  static variable_list backward(AutogradContext* ctx, variable_list grad_outputs) {
    const auto saved = ctx->get_saved_variables();
    const auto &qkv = saved[0], &probs = saved[1], &freqs = saved[2];
    const int64_t heads = ctx->saved_data["heads"].toInt();
    const double scale = ctx->saved_data["scale"].toDouble();
    const auto grad =
        short_attention_backward(qkv, probs, grad_outputs[0].contiguous(), rotary_tables(freqs, qkv.size(1)),
                                 heads, static_cast<float>(scale));
    return {grad, torch::Tensor(), torch::Tensor(), torch::Tensor()};
  }
};

}  // namespace

torch::Tensor short_attention_fused(const torch::Tensor& qkv, int64_t heads, const torch::Tensor& freqs,
                                    double scale) {
  DOJO_CHECK(qkv.dim() == 4 && qkv.scalar_type() == torch::kFloat32 && qkv.device().is_cpu(),
             "short attention: qkv must be float32 [G, L, R, 3E] on the CPU");
  DOJO_CHECK(qkv.size(1) <= kShortAttentionMaxLength,
             "short attention: at most " + std::to_string(kShortAttentionMaxLength) + " positions");
  DOJO_CHECK(heads > 0 && qkv.size(3) % (3 * heads) == 0,
             "short attention: 3 x heads must divide qkv's width");
  const int64_t head_dim = qkv.size(3) / (3 * heads);
  // libtorch 1.13 refuses undefined tensors among a Function's inputs: empty means no rotation.
  auto rotary = torch::empty({0}, qkv.options());
  if (freqs.defined()) {
    DOJO_CHECK(head_dim % 2 == 0 && freqs.numel() == head_dim / 2,
               "short attention: the rotary frequencies must be head_dim / 2 numbers");
    rotary = freqs.detach().to(torch::kFloat32).contiguous();
  }
  if (torch::GradMode::is_enabled() && qkv.requires_grad())
    return ShortAttentionFunction::apply(qkv, rotary, heads, scale);
  return short_attention_forward(qkv.contiguous(), rotary, heads, scale).first;
}

}  // namespace dojo::models
