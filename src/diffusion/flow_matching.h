// Rectified-flow (flow-matching) training pieces of the DreamDojo teacher: logit-normal time
// sampling on the shifted 1000-step grid, the noisy input and velocity target, the loss with the
// temporal-difference term, and the "power" EMA of the weights.
// Facts: ../shared/reference/dreamdojo.md §7-§8, cosmos_dit.md §12.
//
// Conventions: latents are [B, C, T, H, W]; x_t = σ·ε + (1 − σ)·x0, target velocity v = ε − x0,
// so x0 = x_t − σ·v. The network is fed timesteps = 1000·σ (times 0.001 inside the net).
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <vector>

namespace dojo::diffusion {

// Axis of the temporal-consistency loss term (dreamdojo.md §0 row 2). The paper differentiates
// along time; the released code along dim 1 of [B, C, T, H, W], i.e. the channels.
enum class TemporalAxis { kTime, kChannel };

struct FlowMatchingConfig {
  double shift = 5.0;            // σ = shift·s / (1 + (shift − 1)·s) on the training grid
  int grid = 1000;               // number of discrete training times
  double high_sigma_prob = 0.0;  // per sample: replace the time by a grid time in [980, 1000]
  TemporalAxis temporal_axis = TemporalAxis::kTime;
  double temporal_weight = 0.1;  // weight of the temporal-difference MSE

  void validate() const;  // throws dojo::Error naming the bad field
};

struct TrainingNoise {
  torch::Tensor sigma;            // [B] float32, in (0, 1]
  torch::Tensor timesteps;        // [B] float32, network units 1000·σ
  torch::Tensor noise;            // [B, C, T, H, W] ε ~ N(0, I)
  torch::Tensor x_t;              // [B, C, T, H, W] σ·ε + (1 − σ)·x0
  torch::Tensor target_velocity;  // [B, C, T, H, W] ε − x0
};

// The training-grid σ of grid index i: s = (grid − i)/grid, σ = shift·s/(1 + (shift − 1)·s).
double training_grid_sigma(int64_t index, const FlowMatchingConfig& config);

// Draws one time per sample (shared by all frames) and the noise, following dreamdojo.md §7.2-7.5:
// u = sigmoid(n), n ~ N(0, 1); idx = int(u·grid); σ = training_grid_sigma(idx); with probability
// high_sigma_prob the index is instead drawn uniformly among grid points whose timestep lies in
// [980, 1000]. All randomness comes from `gen` (a CPU generator; results are moved to x0's
// device), so a seed gives the same draw on every device. The outputs have x0's dtype, except
// sigma/timesteps (float32).
TrainingNoise sample_training_noise(const torch::Tensor& x0, const FlowMatchingConfig& config,
                                    torch::Generator gen);
TrainingNoise sample_training_noise(const torch::Tensor& x0, const FlowMatchingConfig& config, uint64_t seed);

// Loss per sample: mean(w·(v̂ − v)²) + temporal_weight · mean((Δv̂ − Δv)²), Δ the forward difference
// along the configured axis (time = dim 2, channel = dim 1); returns the batch mean (a scalar,
// float32 or wider). With `per_sample`, also stores the [B] per-sample losses there. Inputs
// [B, C, T, H, W] of equal shape; a size-1 difference axis contributes 0. `weight` (undefined: 1)
// broadcasts against the inputs, e.g. motion_weight's [B, 1, T, H, W].
torch::Tensor flow_matching_loss(const torch::Tensor& pred_velocity, const torch::Tensor& target_velocity,
                                 const FlowMatchingConfig& config, torch::Tensor* per_sample = nullptr,
                                 const torch::Tensor& weight = {});

// Per-position loss weight that favours what moves (Vista's motion-weighted loss, on latents):
// w = 1 + strength · d / mean(d), d the channel-mean |x0[t] − x0[t − 1]| of each latent position
// (d = 0 on frame 0), the mean taken per sample. Moving parts (an arm) are a small share of the
// pixels, so an unweighted loss learns the static background first. x0 [B, C, T, H, W] ->
// [B, 1, T, H, W], no gradient.
torch::Tensor motion_weight(const torch::Tensor& x0, double strength);

// Power EMA (Karras et al. 2024, as configured in DreamDojo, dreamdojo.md §8).
// γ for a relative standard deviation σ_rel: the largest real root of
// σ_rel²·(γ + 2)²·(γ + 3) = γ + 1 (for σ_rel = 0.1: γ³ + 7γ² − 84γ − 88 = 0, γ ≈ 6.9372).
// Valid for 0 < σ_rel < √(1/12) (above that no root is positive); throws dojo::Error otherwise.
double power_ema_gamma(double sigma_rel);
// β(it) = (1 − 1/(it + 1))^(γ + 1); β(0) = 0, so the first update copies the weights.
double power_ema_beta(int64_t iteration, double gamma);
// ema ← β·ema + (1 − β)·param, in place and without autograd. Same count and shapes required
// (dtype may differ, e.g. float32 EMA of bf16 weights).
void ema_update(std::vector<torch::Tensor>& ema, const std::vector<torch::Tensor>& params, double beta);

}  // namespace dojo::diffusion
