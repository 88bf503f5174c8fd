#include "diffusion/samplers.h"

#include <c10/util/BFloat16.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>
#include <utility>

#include "core/error.h"

namespace dojo::diffusion {

namespace {

// UniPC's half-log-SNR of the flow parameterisation: α = 1 − σ, λ = ln α − ln σ (+∞ at σ = 0).
double flow_lambda(double sigma) {
  if (sigma <= 0) return std::numeric_limits<double>::infinity();
  return std::log(1.0 - sigma) - std::log(sigma);
}

double round_bf16(double v) {
  // double -> float -> bf16 (round to nearest even), as torch.full(..., dtype=torch.bfloat16) does.
  return static_cast<float>(c10::BFloat16(static_cast<float>(v)));
}

}  // namespace

SigmaSchedule flow_sigma_schedule(int num_steps, double shift) {
  DOJO_CHECK(num_steps >= 1, "flow_sigma_schedule: num_steps must be >= 1, got " + std::to_string(num_steps));
  DOJO_CHECK(shift > 0, "flow_sigma_schedule: shift must be > 0, got " + std::to_string(shift));
  // The training sigmas 1 − linspace(1, 1/1000, 1000)[::-1] are stored as float32, so the reference
  // reads σ_max back as float32(0.999); σ_min is exactly 0.
  const double sigma_max = static_cast<float>(1.0 - 1.0 / 1000.0);
  const double sigma_min = 0.0;
  // numpy.linspace(start, stop, N + 1): start + k·((stop − start)/N); only the first N are used.
  const double delta = (sigma_min - sigma_max) / num_steps;
  SigmaSchedule out;
  for (int k = 0; k < num_steps; ++k) {
    const double s = k * delta + sigma_max;
    const double warped = shift * s / (1.0 + (shift - 1.0) * s);
    out.timesteps.push_back(static_cast<int64_t>(warped * 1000.0));
    out.sigmas.push_back(static_cast<float>(warped));
  }
  out.sigmas.push_back(0.0);
  return out;
}

FlowSampler::FlowSampler(SigmaSchedule schedule, Solver solver)
    : schedule_(std::move(schedule)), solver_(solver) {
  DOJO_CHECK(schedule_.num_steps() >= 1 && schedule_.sigmas.size() == schedule_.timesteps.size() + 1,
             "FlowSampler: schedule needs N >= 1 timesteps and N + 1 sigmas");
}

torch::Tensor FlowSampler::step(const torch::Tensor& x, const torch::Tensor& velocity) {
  const int n = num_steps();
  const int k = step_;
  DOJO_CHECK(k < n, "FlowSampler: all " + std::to_string(n) + " steps are done");
  DOJO_CHECK(x.sizes() == velocity.sizes(), "FlowSampler: sample and velocity shapes differ");
  const auto& sig = schedule_.sigmas;
  const double sigma_s = sig[k];
  const double sigma_t = sig[k + 1];
  const auto x0_pred = x - sigma_s * velocity;  // the model output UniPC keeps: x0 prediction

  if (solver_ == Solver::kEuler) {
    x0_history_.assign({x0_pred});
    ++step_;
    return x + (sigma_t - sigma_s) * velocity;
  }

  // 1. UniC corrector: refine the sample the previous predictor produced (x), using the fresh
  //    x0 prediction at it, with the order of that predictor.
  torch::Tensor sample = x;
  if (k > 0) {
    const auto& m_prev = x0_history_.back();  // m_{k-1}
    const double lambda_t = flow_lambda(sig[k]);
    const double lambda_s = flow_lambda(sig[k - 1]);
    const double h = lambda_t - lambda_s;
    const double hh = -h;
    const double phi_1 = std::expm1(hh);
    const double b_h = phi_1;  // bh2
    const double alpha_t = 1.0 - sig[k];
    double rho_d = 0.0;     // weight of D1 (order 2 only)
    double rho_last = 0.5;  // weight of m_k − m_{k-1}
    torch::Tensor d1;
    if (last_order_ == 2) {
      const double r = (flow_lambda(sig[k - 2]) - lambda_s) / h;
      d1 = (x0_history_[x0_history_.size() - 2] - m_prev) / r;
      // Solve [[1, 1], [r, 1]]·ρ = b with b_i from the φ-function expansion (factorials 1, 2).
      const double b1 = (phi_1 / hh - 1.0) / b_h;
      const double b2 = ((phi_1 / hh - 1.0) / hh - 0.5) * 2.0 / b_h;
      rho_d = (b1 - b2) / (1.0 - r);
      rho_last = b1 - rho_d;
    }
    auto corrected = (sig[k] / sig[k - 1]) * last_sample_ - (alpha_t * phi_1) * m_prev;
    auto residual = rho_last * (x0_pred - m_prev);
    if (d1.defined()) residual = residual + rho_d * d1;
    sample = corrected - (alpha_t * b_h) * residual;
  }

  x0_history_.push_back(x0_pred);
  if (x0_history_.size() > 2) x0_history_.erase(x0_history_.begin());

  // Order schedule: warm up from 1, at most 2, and 1 at the last step (lower_order_final).
  const int order = std::min({2, n - k, k + 1});
  last_order_ = order;
  last_sample_ = sample;
  ++step_;

  // 2. UniP predictor to σ_t. At σ_t = 0 (λ = +∞, φ₁ = B = −1) it returns the x0 prediction.
  if (sigma_t <= 0) return x0_pred;
  const double lambda_t = flow_lambda(sigma_t);
  const double lambda_s = flow_lambda(sigma_s);
  const double h = lambda_t - lambda_s;
  const double hh = -h;
  const double phi_1 = std::expm1(hh);
  const double b_h = phi_1;
  const double alpha_t = 1.0 - sigma_t;
  auto next = (sigma_t / sigma_s) * sample - (alpha_t * phi_1) * x0_pred;
  if (order == 2) {
    const double r = (flow_lambda(sig[k - 1]) - lambda_s) / h;
    const auto d1 = (x0_history_.front() - x0_pred) / r;  // (m_{k-1} − m_k)/r
    next = next - (alpha_t * b_h * 0.5) * d1;             // order-2 predictor weight ρ = 0.5
  }
  return next;
}

const torch::Tensor& FlowSampler::last_x0_pred() const {
  DOJO_CHECK(!x0_history_.empty(), "FlowSampler: no step taken yet, so there is no x0 prediction");
  return x0_history_.back();
}

torch::Tensor sample_flow(const VelocityFn& velocity, torch::Tensor noise, const SigmaSchedule& schedule,
                          Solver solver, std::vector<torch::Tensor>* trajectory,
                          const std::function<void(int)>& on_step) {
  FlowSampler sampler(schedule, solver);
  torch::Tensor x = std::move(noise);
  if (trajectory) {
    trajectory->clear();
    trajectory->push_back(x);
  }
  for (int i = 0; i < sampler.num_steps(); ++i) {
    const auto v = velocity(x, sampler.sigma(i), sampler.timestep(i));
    DOJO_CHECK(v.sizes() == x.sizes(),
               "sample_flow: the velocity function returned a wrong shape at step " + std::to_string(i));
    x = sampler.step(x, v);
    if (trajectory) trajectory->push_back(x);
    if (on_step) on_step(i);
  }
  return x;
}

std::vector<StudentStep> student_schedule(bool bf16_times) {
  const double pi = std::acos(-1.0);
  const double times[4] = {pi / 2, std::atan(15.0), std::atan(5.0), std::atan(5.0 / 3.0)};
  std::vector<StudentStep> out;
  for (double t : times) {
    if (bf16_times) t = round_bf16(t);
    const double denom = std::cos(t) + std::sin(t);
    StudentStep s;
    s.trigflow_t = t;
    s.rf_sigma = std::sin(t) / denom;
    s.c_skip = 1.0 / denom;
    s.c_out = -std::sin(t) / denom;
    s.c_in = 1.0 / denom;
    s.c_noise = std::sin(t) / denom;
    if (bf16_times) {
      s.c_skip = round_bf16(s.c_skip);
      s.c_out = round_bf16(s.c_out);
      s.c_in = round_bf16(s.c_in);
      s.c_noise = round_bf16(s.c_noise);
    }
    out.push_back(s);
  }
  return out;
}

double student_t_cond() { return std::atan(1e-4); }

}  // namespace dojo::diffusion
