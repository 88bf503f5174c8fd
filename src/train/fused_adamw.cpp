#include "train/fused_adamw.h"

#include <ATen/Parallel.h>
#include <torch/nn/utils/clip_grad.h>
#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <limits>
#include <string>

#include "core/error.h"
#include "core/runtime.h"
#include "diffusion/flow_matching.h"
#include "train/train_util.h"

namespace dojo::train {
namespace {

// Copies `tensors` into one new flat buffer and makes each a view of its slice (same identity,
// same shape). -> the buffer [N]
torch::Tensor flatten_into_views(const std::vector<torch::Tensor>& tensors,
                                 const std::vector<int64_t>& offsets, int64_t total,
                                 const torch::TensorOptions& options) {
  torch::NoGradGuard no_grad;
  auto flat = torch::empty({total}, options);
  for (size_t i = 0; i < tensors.size(); ++i) {
    auto t = tensors[i];
    const auto n = t.numel();
    flat.narrow(0, offsets[i], n).copy_(t.reshape({n}));
    // set_ keeps the TensorImpl (modules, the optimizer's state keys and autograd see the same
    // tensor); a contiguous view of the buffer's storage replaces its own storage.
    t.set_(flat.narrow(0, offsets[i], n).view(t.sizes()));
  }
  return flat;
}

torch::optim::AdamWOptions& adamw_options(torch::optim::AdamW& optimizer) {
  DOJO_CHECK(optimizer.param_groups().size() == 1, "FusedAdamW: the optimizer must have one parameter group");
  return static_cast<torch::optim::AdamWOptions&>(optimizer.param_groups()[0].options());
}

}  // namespace

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
// AVX2 where the CPU has it: the loop is memory-bound, but 8 lanes keep the arithmetic (a square
// root and a division per element) off the critical path.
__attribute__((target_clones("avx2", "default")))
#endif
void fused_adamw_update(float* __restrict param, const float* __restrict grad, float* __restrict exp_avg,
                        float* __restrict exp_avg_sq, float* __restrict ema, int64_t n, const AdamwScalars& s) {
  const float decay = static_cast<float>(1.0 - s.lr * s.weight_decay);
  const float b1 = static_cast<float>(s.beta1), one_minus_b1 = static_cast<float>(1.0 - s.beta1);
  const float b2 = static_cast<float>(s.beta2), one_minus_b2 = static_cast<float>(1.0 - s.beta2);
  const float scale = static_cast<float>(s.grad_scale);
  const float sqrt_bc2 = static_cast<float>(std::sqrt(1.0 - std::pow(s.beta2, static_cast<double>(s.step))));
  const float step_size = static_cast<float>(s.lr / (1.0 - std::pow(s.beta1, static_cast<double>(s.step))));
  const float eps = static_cast<float>(s.eps);
  const float keep = static_cast<float>(s.ema_beta), take = static_cast<float>(1.0 - s.ema_beta);
  for (int64_t i = 0; i < n; ++i) {
    const float g = grad[i] * scale;
    const float m = exp_avg[i] * b1 + g * one_minus_b1;
    const float v = exp_avg_sq[i] * b2 + g * g * one_minus_b2;
    const float p = param[i] * decay - step_size * (m / (std::sqrt(v) / sqrt_bc2 + eps));
    exp_avg[i] = m;
    exp_avg_sq[i] = v;
    param[i] = p;
    if (ema != nullptr) ema[i] = ema[i] * keep + p * take;
  }
}

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
__attribute__((target_clones("avx2", "default")))
#endif
void fused_ema_update(float* __restrict ema, const float* __restrict param, int64_t n, double ema_beta) {
  // The EMA line of fused_adamw_update, the same arithmetic (so the same bits) on its own.
  const float keep = static_cast<float>(ema_beta), take = static_cast<float>(1.0 - ema_beta);
  for (int64_t i = 0; i < n; ++i) ema[i] = ema[i] * keep + param[i] * take;
}

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
__attribute__((target_clones("avx2", "default")))
#endif
double
fused_squared_sum(const float* __restrict x, int64_t n) {
  // Double lanes: a float running sum over millions of squares drifts by parts per thousand
  // (libtorch 1.13's own float norm of the small DiT's 11.4M gradients was 0.1-0.4 % off).
  double lanes[4] = {0, 0, 0, 0};
  int64_t i = 0;
  for (; i + 4 <= n; i += 4)
    for (int j = 0; j < 4; ++j) lanes[j] += static_cast<double>(x[i + j]) * x[i + j];
  for (; i < n; ++i) lanes[0] += static_cast<double>(x[i]) * x[i];
  return (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
}

FusedAdamW::FusedAdamW(torch::optim::AdamW& optimizer, std::vector<torch::Tensor> params,
                       std::vector<torch::Tensor> ema)
    : optimizer_(optimizer), params_(std::move(params)), ema_(std::move(ema)) {
  DOJO_CHECK(!params_.empty(), "FusedAdamW: no parameters");
  DOJO_CHECK(ema_.empty() || ema_.size() == params_.size(),
             "FusedAdamW: " + std::to_string(ema_.size()) + " EMA tensors for " +
                 std::to_string(params_.size()) + " parameters");
  DOJO_CHECK(!adamw_options(optimizer_).amsgrad(), "FusedAdamW: amsgrad is not supported");
  const auto options = params_.front().options();
  int64_t total = 0;
  for (size_t i = 0; i < params_.size(); ++i) {
    const auto& p = params_[i];
    DOJO_CHECK(p.scalar_type() == torch::kFloat32 && p.device() == options.device() && p.requires_grad(),
               "FusedAdamW: parameters must be float32 tensors on one device that require gradients");
    DOJO_CHECK(ema_.empty() || (ema_[i].sizes() == p.sizes() && ema_[i].scalar_type() == torch::kFloat32 &&
                                ema_[i].device() == p.device()),
               "FusedAdamW: EMA tensor " + std::to_string(i) + " differs from its parameter");
    offsets_.push_back(total);
    total += p.numel();
  }
  param_ = flatten_into_views(params_, offsets_, total, options);
  if (!ema_.empty()) ema_flat_ = flatten_into_views(ema_, offsets_, total, options);
  grad_ = torch::zeros({total}, options);
  // The moments are made at the first step or state adopted (make_moments): a trainer that
  // shards before then never holds the whole of them.
  exp_avg_ = torch::zeros({0}, options);
  exp_avg_sq_ = torch::zeros({0}, options);
  for (size_t i = 0; i < params_.size(); ++i)
    params_[i].mutable_grad() = grad_.narrow(0, offsets_[i], params_[i].numel()).view(params_[i].sizes());
  begin_ = 0;
  own_ = shard_ = total;
  adopt_state();
}

void FusedAdamW::zero_grad() {
  for (size_t i = 0; i < params_.size(); ++i)
    DOJO_CHECK(params_[i].grad().defined() &&
                   params_[i].grad().data_ptr<float>() == grad_.data_ptr<float>() + offsets_[i],
               "FusedAdamW: a gradient was replaced (zero_grad(set_to_none) or an assignment); the flat "
               "gradient no longer holds it");
  grad_.zero_();
  // Moments gathered for a save (gather_state) go before this step's activations are made.
  if (sharded()) optimizer_.state().clear();
}

void FusedAdamW::point_state(const torch::Tensor& m, const torch::Tensor& v) {
  auto& state = optimizer_.state();
  for (size_t i = 0; i < params_.size(); ++i) {
    const auto& p = params_[i];
    auto st = std::make_unique<torch::optim::AdamWParamState>();
    st->exp_avg(m.narrow(0, offsets_[i], p.numel()).view(p.sizes()));
    st->exp_avg_sq(v.narrow(0, offsets_[i], p.numel()).view(p.sizes()));
    st->step(step_);
    state[optimizer_state_key(p)] = std::move(st);
  }
}

void FusedAdamW::adopt_state() {
  torch::NoGradGuard no_grad;
  auto& state = optimizer_.state();
  int64_t found = 0;
  step_ = 0;
  for (size_t i = 0; i < params_.size(); ++i) {
    const auto& p = params_[i];
    auto it = state.find(optimizer_state_key(p));
    if (it == state.end()) continue;
    const auto& st = static_cast<const torch::optim::AdamWParamState&>(*it->second);
    DOJO_CHECK(found == 0 || st.step() == step_,
               "FusedAdamW: the optimizer's parameters are at different steps");
    step_ = st.step();
    make_moments();
    // The part of this parameter that lies in the moments held here (all of it unsharded).
    const int64_t from = std::max(offsets_[i], begin_), to = std::min(offsets_[i] + p.numel(), begin_ + own_);
    if (from < to) {
      exp_avg_.narrow(0, from - begin_, to - from)
          .copy_(st.exp_avg().reshape({p.numel()}).narrow(0, from - offsets_[i], to - from));
      exp_avg_sq_.narrow(0, from - begin_, to - from)
          .copy_(st.exp_avg_sq().reshape({p.numel()}).narrow(0, from - offsets_[i], to - from));
    }
    ++found;
  }
  DOJO_CHECK(found == 0 || found == static_cast<int64_t>(params_.size()),
             "FusedAdamW: optimizer state for " + std::to_string(found) + " of " +
                 std::to_string(params_.size()) + " parameters");
  if (sharded())
    state.clear();  // the whole moments of a resumed state: this rank keeps its slice only
  else if (found > 0)
    point_state(exp_avg_, exp_avg_sq_);
}

void FusedAdamW::shard(Collectives collectives) {
  const int world = collectives.world, rank = collectives.rank;
  DOJO_CHECK(world >= 1 && rank >= 0 && rank < world && collectives.all_gather && collectives.gather_to_main,
             "FusedAdamW: rank " + std::to_string(rank) + " of " + std::to_string(world));
  DOJO_CHECK(!plain_kernels() || world == 1,
             "FusedAdamW: sharded optimizer state (ZeRO-1) has no plain path; unset DOJO_PLAIN_KERNELS");
  DOJO_CHECK(!sharded(), "FusedAdamW: already sharded");
  if (world == 1) return;
  torch::NoGradGuard no_grad;
  const int64_t total = param_.numel();
  collectives_ = std::move(collectives);
  shard_ = (total + world - 1) / world;
  begin_ = std::min(total, rank * shard_);
  own_ = std::min(total, begin_ + shard_) - begin_;
  // Moments adopted so far (a resumed state) keep their slice; the rest of them is freed.
  if (exp_avg_.numel() > 0) {
    exp_avg_ = exp_avg_.narrow(0, begin_, own_).clone();
    exp_avg_sq_ = exp_avg_sq_.narrow(0, begin_, own_).clone();
  }
  optimizer_.state().clear();
}

void FusedAdamW::make_moments() {
  if (exp_avg_.numel() == own_) return;
  exp_avg_ = torch::zeros({own_}, param_.options());
  exp_avg_sq_ = torch::zeros({own_}, param_.options());
}

void FusedAdamW::gather_slices(const torch::Tensor& mine, const torch::Tensor& whole, bool into_main) {
  // 2 Mi elements (8 MiB) a collective: Gloo stages each in a buffer of world x that size.
  constexpr int64_t kChunk = int64_t{1} << 21;
  const int64_t total = param_.numel();
  const int world = collectives_.world;
  const bool receives = !into_main || collectives_.rank == 0;
  for (int64_t at = 0; at < shard_; at += kChunk) {
    const int64_t n = std::min(kChunk, shard_ - at);
    // This rank's part (zero-padded where its slice ends early: every rank sends n elements).
    auto send = at + n <= own_ ? mine.narrow(0, at, n) : torch::zeros({n}, mine.options());
    if (at < own_ && at + n > own_) send.narrow(0, 0, own_ - at).copy_(mine.narrow(0, at, own_ - at));
    std::vector<torch::Tensor> out;
    std::vector<std::pair<int, int64_t>> partial;  // (rank, elements) received into a temporary
    for (int r = 0; receives && r < world; ++r) {
      const int64_t from = r * shard_ + at, fits = std::max<int64_t>(0, std::min(n, total - from));
      if (fits == n) {
        out.push_back(whole.narrow(0, from, n));
      } else {
        out.push_back(torch::empty({n}, whole.options()));
        partial.emplace_back(r, fits);
      }
    }
    (into_main ? collectives_.gather_to_main : collectives_.all_gather)(send, out);
    for (const auto& [r, fits] : partial)
      if (fits > 0) whole.narrow(0, r * shard_ + at, fits).copy_(out[r].narrow(0, 0, fits));
  }
}

void FusedAdamW::gather_state() {
  if (!sharded() || step_ == 0) return;
  torch::NoGradGuard no_grad;
  // Into host memory: the checkpoint is written from there, and a device does not have to find
  // room for the whole moments beside the training state it sharded them to make room for.
  const bool main = collectives_.rank == 0;
  const auto host = param_.options().device(torch::kCPU);
  auto m = main ? torch::empty({param_.numel()}, host) : torch::Tensor(),
       v = main ? torch::empty({param_.numel()}, host) : torch::Tensor();
  gather_slices(exp_avg_.to(torch::kCPU), m, /*into_main=*/true);
  gather_slices(exp_avg_sq_.to(torch::kCPU), v, /*into_main=*/true);
  if (main) point_state(m, v);
}

void FusedAdamW::plain_step(double max_norm, double lr, double ema_beta, double& norm) {
  norm = torch::nn::utils::clip_grad_norm_(params_, max_norm);
  adamw_options(optimizer_).lr(lr);
  optimizer_.step();
  if (!ema_.empty()) diffusion::ema_update(ema_, params_, ema_beta);
}

double FusedAdamW::step(double max_norm, double lr, double ema_beta) {
  torch::NoGradGuard no_grad;
  if (!(max_norm > 0)) max_norm = std::numeric_limits<double>::infinity();
  make_moments();
  // (Sharded: moments gathered for a save were freed by zero_grad().)
  if (!sharded() && step_ == 0) point_state(exp_avg_, exp_avg_sq_);  // from the first step on, as views
  double norm = 0;
  if (plain_kernels()) {
    plain_step(max_norm, lr, ema_beta, norm);
    ++step_;
    return norm;
  }
  if (grad_.is_cpu()) {
    const float* g = grad_.data_ptr<float>();
    norm = std::sqrt(at::parallel_reduce(
        0, grad_.numel(), 1 << 16, 0.0,
        [&](int64_t begin, int64_t end, double partial) {
          return partial + fused_squared_sum(g + begin, end - begin);
        },
        std::plus<double>()));
  } else {
    norm = grad_.to(torch::kDouble).norm().item<double>();
  }
  // As clip_grad_norm_: scaled only when the coefficient is below 1 (a NaN norm scales nothing).
  const double coef = max_norm / (norm + 1e-6);
  auto& o = adamw_options(optimizer_);
  o.lr(lr);
  ++step_;
  AdamwScalars s{lr,
                 std::get<0>(o.betas()),
                 std::get<1>(o.betas()),
                 o.eps(),
                 o.weight_decay(),
                 coef < 1.0 ? coef : 1.0,
                 ema_beta,
                 step_};
  // The elements whose moments are held here: all of them, or this rank's slice.
  if (param_.is_cpu()) {
    float* p = param_.data_ptr<float>() + begin_;
    const float* g = grad_.data_ptr<float>() + begin_;
    float* m = exp_avg_.data_ptr<float>();
    float* v = exp_avg_sq_.data_ptr<float>();
    float* e = ema_flat_.defined() ? ema_flat_.data_ptr<float>() + begin_ : nullptr;
    at::parallel_for(0, own_, 1 << 16, [&](int64_t begin, int64_t end) {
      fused_adamw_update(p + begin, g + begin, m + begin, v + begin, e != nullptr ? e + begin : nullptr,
                         end - begin, s);
    });
  } else {
    // Other devices: the same update as a few whole-buffer operations.
    auto param = param_.narrow(0, begin_, own_);
    const auto g = grad_.narrow(0, begin_, own_) * s.grad_scale;
    param.mul_(1 - lr * s.weight_decay);
    exp_avg_.mul_(s.beta1).add_(g, 1 - s.beta1);
    exp_avg_sq_.mul_(s.beta2).addcmul_(g, g, 1 - s.beta2);
    const double bc1 = 1 - std::pow(s.beta1, static_cast<double>(step_));
    const double bc2 = 1 - std::pow(s.beta2, static_cast<double>(step_));
    param.addcdiv_(exp_avg_, (exp_avg_sq_.sqrt() / std::sqrt(bc2)).add_(s.eps), -lr / bc1);
    if (ema_flat_.defined()) ema_flat_.narrow(0, begin_, own_).mul_(ema_beta).add_(param, 1 - ema_beta);
  }
  if (sharded()) {
    // Every rank's updated slice of the parameters, into place on every rank; then the EMA of the
    // other ranks' elements here (the same arithmetic as the fused update: the same bits).
    gather_slices(param_.narrow(0, begin_, own_), param_, /*into_main=*/false);
    if (ema_flat_.defined()) {
      const int64_t total = param_.numel(), end = begin_ + own_;
      if (param_.is_cpu()) {
        float* e = ema_flat_.data_ptr<float>();
        const float* p = param_.data_ptr<float>();
        for (const auto& [from, to] : {std::pair{int64_t{0}, begin_}, std::pair{end, total}})
          at::parallel_for(from, to, 1 << 16,
                           [&](int64_t b, int64_t f) { fused_ema_update(e + b, p + b, f - b, ema_beta); });
      } else {
        for (const auto& [from, to] : {std::pair{int64_t{0}, begin_}, std::pair{end, total}})
          if (to > from)
            ema_flat_.narrow(0, from, to - from)
                .mul_(ema_beta)
                .add_(param_.narrow(0, from, to - from), 1 - ema_beta);
      }
    }
  } else {
    for (const auto& p : params_)
      static_cast<torch::optim::AdamWParamState&>(*optimizer_.state().at(optimizer_state_key(p))).step(step_);
  }
  return norm;
}

}  // namespace dojo::train
