// Samplers for the rectified-flow teacher and the time tables of the few-step student.
// Facts: ../shared/reference/cosmos_dit.md §13, dreamdojo.md §9, self_forcing.md §3.1; parity
// fixture ../shared/golden/flow_sampler.md.
//
// The network is abstracted as a velocity function v̂(x, σ, timestep) over the whole batch, so
// this file does not depend on the DiT. Conventions: x_σ = σ·ε + (1 − σ)·x0, v = ε − x0,
// x0 prediction m = x − σ·v̂.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <functional>
#include <vector>

namespace dojo::diffusion {

// The inference σ grid of FlowUniPCMultistepScheduler(num_train_timesteps=1000, shift=1) after
// set_timesteps(N, shift): σ_k = linspace(σ_max, 0, N + 1)[k] for k < N with σ_max = float32(0.999),
// warped σ'_k = shift·σ_k/(1 + (shift − 1)·σ_k), then a final σ = 0.
struct SigmaSchedule {
  std::vector<double> sigmas;      // N + 1, float32-rounded as the reference stores them; last is 0
  std::vector<int64_t> timesteps;  // N, int64(1000·σ'_k) computed in double: TRUNCATED
  int num_steps() const { return static_cast<int>(timesteps.size()); }
};
SigmaSchedule flow_sigma_schedule(int num_steps, double shift = 5.0);

// v̂ for the whole batch x at one step: σ is the solver's (untruncated) noise level, timestep the
// truncated integer the network sees (it multiplies by 0.001 itself).
using VelocityFn = std::function<torch::Tensor(const torch::Tensor& x, double sigma, int64_t timestep)>;

enum class Solver { kEuler, kUniPC };

// One sampler run, stepped by the caller (sample_flow drives it; a caller that must act between
// steps, e.g. to stream previews, can drive it directly).
//   FlowSampler s(schedule, Solver::kUniPC);
//   for (int i = 0; i < s.num_steps(); ++i) x = s.step(x, velocity(x, s.sigma(i), s.timestep(i)));
class FlowSampler {
 public:
  FlowSampler(SigmaSchedule schedule, Solver solver);

  int num_steps() const { return schedule_.num_steps(); }
  int step_index() const { return step_; }  // steps done so far
  double sigma(int i) const { return schedule_.sigmas.at(i); }
  int64_t timestep(int i) const { return schedule_.timesteps.at(i); }

  // Advances x (the sample at σ_{step_index()}) with the velocity v̂ evaluated there; returns the
  // sample at the next σ. UniPC: order-2 bh2 multistep predictor with the UniC corrector, order 1
  // at the first and last step, exactly as the reference scheduler (cosmos_dit.md §13.2).
  // Euler: x + (σ_next − σ)·v̂. Throws dojo::Error when called more than num_steps() times.
  torch::Tensor step(const torch::Tensor& x, const torch::Tensor& velocity);
  // The x0 prediction x − σ·v̂ of the last step() (what UniPC stores as its model output).
  // Throws dojo::Error before the first step.
  const torch::Tensor& last_x0_pred() const;

 private:
  SigmaSchedule schedule_;
  Solver solver_;
  int step_ = 0;
  int last_order_ = 0;                     // order of the previous predictor (the corrector reuses it)
  torch::Tensor last_sample_;              // the sample the previous predictor started from
  std::vector<torch::Tensor> x0_history_;  // x0 predictions, newest last (at most 2 kept)
};

// Integrates from `noise` (the sample at σ_0) to σ = 0. `trajectory`, when given, receives the
// N + 1 samples (noise first, the result last); `on_step(i)` is called after step i.
torch::Tensor sample_flow(const VelocityFn& velocity, torch::Tensor noise, const SigmaSchedule& schedule,
                          Solver solver, std::vector<torch::Tensor>* trajectory = nullptr,
                          const std::function<void(int)>& on_step = {});

// One hop of the 4-step Self-Forcing student (TrigFlow time t, σ_data = 1, RectifiedFlow_sCMWrapper):
// x0̂ = c_skip·x_t + c_out·v̂(c_in·x_t, c_noise), re-noise x = cos(t_next)·x0̂ + sin(t_next)·ε.
struct StudentStep {
  double trigflow_t;  // t ∈ (0, π/2]
  double rf_sigma;    // sin t/(cos t + sin t): the rectified-flow σ of this time (= c_noise)
  double c_skip;      // 1/(cos t + sin t)
  double c_out;       // −sin t/(cos t + sin t)
  double c_in;        // 1/(cos t + sin t)
  double c_noise;     // sin t/(cos t + sin t), fed to the net as its time (timestep_scale 1)
};
// Times [π/2, atan 15, atan 5, atan 5/3] (σ = [1, 15/16, 5/6, 5/8]). With bf16_times, t is
// rounded to bfloat16 as the released streaming code creates it, and the coefficients (computed in
// float64 from the rounded t) are rounded to bfloat16 again, as the released wrapper returns
// them in the input's dtype; rf_sigma is then the unrounded σ of the rounded t.
std::vector<StudentStep> student_schedule(bool bf16_times);
// TrigFlow time of a conditioning frame: atan(σ_cond), σ_cond = 1e-4.
double student_t_cond();

}  // namespace dojo::diffusion
