#include "diffusion/flow_matching.h"

#include <ATen/CPUGeneratorImpl.h>

#include <algorithm>
#include <cmath>
#include <string>

#include "core/error.h"

namespace dojo::diffusion {

void FlowMatchingConfig::validate() const {
  DOJO_CHECK(shift > 0, "flow matching: shift must be > 0, got " + std::to_string(shift));
  DOJO_CHECK(grid >= 1, "flow matching: grid must be >= 1, got " + std::to_string(grid));
  DOJO_CHECK(high_sigma_prob >= 0 && high_sigma_prob <= 1,
             "flow matching: high_sigma_prob must be in [0, 1], got " + std::to_string(high_sigma_prob));
  DOJO_CHECK(temporal_weight >= 0,
             "flow matching: temporal_weight must be >= 0, got " + std::to_string(temporal_weight));
}

double training_grid_sigma(int64_t index, const FlowMatchingConfig& config) {
  const double s = static_cast<double>(config.grid - index) / config.grid;
  return config.shift * s / (1.0 + (config.shift - 1.0) * s);
}

TrainingNoise sample_training_noise(const torch::Tensor& x0, const FlowMatchingConfig& config,
                                    torch::Generator gen) {
  config.validate();
  DOJO_CHECK(x0.dim() == 5,
             "flow matching: x0 must be [B, C, T, H, W], got " + std::to_string(x0.dim()) + " dims");
  const int64_t batch = x0.size(0);
  const auto f64 = torch::TensorOptions().dtype(torch::kDouble);

  // Logit-normal u; small u means high noise (index 0 is σ = 1).
  const auto u = torch::sigmoid(torch::randn({batch}, gen, f64));  // [B]
  std::vector<int64_t> index(batch);
  for (int64_t b = 0; b < batch; ++b) {
    const auto i = static_cast<int64_t>(u[b].item<double>() * config.grid);
    index[b] = std::min<int64_t>(std::max<int64_t>(i, 0), config.grid - 1);
  }

  if (config.high_sigma_prob > 0) {
    // Grid points whose network timestep is in [980, 1000]: the lowest indices.
    std::vector<int64_t> high;
    for (int64_t i = 0; i < config.grid; ++i)
      if (1000.0 * training_grid_sigma(i, config) >= 980.0) high.push_back(i);
    DOJO_CHECK(!high.empty(), "flow matching: no grid timestep in [980, 1000] for high_sigma_prob");
    const auto coin = torch::rand({batch}, gen, f64);  // [B]
    const auto pick = torch::randint(static_cast<int64_t>(high.size()), {batch}, gen,
                                     torch::TensorOptions().dtype(torch::kLong));  // [B]
    for (int64_t b = 0; b < batch; ++b)
      if (coin[b].item<double>() < config.high_sigma_prob) index[b] = high[pick[b].item<int64_t>()];
  }

  std::vector<float> sigma(batch), timesteps(batch);
  for (int64_t b = 0; b < batch; ++b) {
    const double s = training_grid_sigma(index[b], config);
    sigma[b] = static_cast<float>(s);
    timesteps[b] = static_cast<float>(1000.0 * s);
  }

  TrainingNoise out;
  const auto f32 = torch::TensorOptions().dtype(torch::kFloat);
  out.sigma = torch::tensor(sigma, f32).to(x0.device());          // [B]
  out.timesteps = torch::tensor(timesteps, f32).to(x0.device());  // [B]
  out.noise = torch::randn(x0.sizes(), gen, f32).to(x0.options());
  const auto s = out.sigma.view({batch, 1, 1, 1, 1}).to(x0.scalar_type());  // [B, 1, 1, 1, 1]
  out.x_t = s * out.noise + (1 - s) * x0;                                   // [B, C, T, H, W]
  out.target_velocity = out.noise - x0;                                     // [B, C, T, H, W]
  return out;
}

TrainingNoise sample_training_noise(const torch::Tensor& x0, const FlowMatchingConfig& config,
                                    uint64_t seed) {
  return sample_training_noise(x0, config, at::make_generator<at::CPUGeneratorImpl>(seed));
}

torch::Tensor motion_weight(const torch::Tensor& x0, double strength) {
  torch::NoGradGuard no_grad;
  DOJO_CHECK(x0.dim() == 5, "motion_weight: latents must be [B, C, T, H, W]");
  const int64_t T = x0.size(2);
  auto d = torch::zeros({x0.size(0), 1, T, x0.size(3), x0.size(4)}, x0.options());  // [B, 1, T, H, W]
  if (T > 1)
    d.narrow(2, 1, T - 1).copy_((x0.narrow(2, 1, T - 1) - x0.narrow(2, 0, T - 1)).abs().mean(1, true));
  const auto mean = d.reshape({d.size(0), -1}).mean(1).clamp_min(1e-8).view({-1, 1, 1, 1, 1});
  return 1.0 + strength * d / mean;
}

torch::Tensor flow_matching_loss(const torch::Tensor& pred_velocity, const torch::Tensor& target_velocity,
                                 const FlowMatchingConfig& config, torch::Tensor* per_sample,
                                 const torch::Tensor& weight) {
  DOJO_CHECK(pred_velocity.dim() == 5, "flow_matching_loss: prediction must be [B, C, T, H, W], got " +
                                           std::to_string(pred_velocity.dim()) + " dims");
  DOJO_CHECK(pred_velocity.sizes() == target_velocity.sizes(),
             "flow_matching_loss: prediction and target shapes differ");
  // bf16 predictions are compared in float32 (the released model computes the loss in fp32).
  auto pred = pred_velocity;
  auto target = target_velocity;
  if (!at::isFloatingType(pred.scalar_type()) || c10::elementSize(pred.scalar_type()) < 4)
    pred = pred.to(torch::kFloat);
  if (target.scalar_type() != pred.scalar_type()) target = target.to(pred.scalar_type());

  const int64_t batch = pred.size(0);
  auto squared = (pred - target).pow(2);
  if (weight.defined()) squared = squared * weight.to(squared.scalar_type());
  auto loss = squared.reshape({batch, -1}).mean(1);  // [B]
  const int64_t axis = config.temporal_axis == TemporalAxis::kTime ? 2 : 1;
  const int64_t len = pred.size(axis);
  if (config.temporal_weight != 0 && len > 1) {
    const auto diff = [&](const torch::Tensor& t) {
      return t.narrow(axis, 1, len - 1) - t.narrow(axis, 0, len - 1);
    };
    const auto temporal = (diff(pred) - diff(target)).pow(2).reshape({batch, -1}).mean(1);  // [B]
    loss = loss + config.temporal_weight * temporal;
  }
  if (per_sample) *per_sample = loss;
  return loss.mean();
}

double power_ema_gamma(double sigma_rel) {
  const double max_sigma = std::sqrt(1.0 / 12.0);
  DOJO_CHECK(sigma_rel > 0 && sigma_rel < max_sigma, "power EMA: sigma_rel must be in (0, " +
                                                         std::to_string(max_sigma) + "), got " +
                                                         std::to_string(sigma_rel));
  // f(γ) = σ²(γ+2)²(γ+3) − (γ+1) = σ²γ³ + 7σ²γ² + (16σ² − 1)γ + (12σ² − 1).
  const double s2 = sigma_rel * sigma_rel;
  const auto f = [&](double g) { return s2 * (g + 2) * (g + 2) * (g + 3) - (g + 1); };
  const auto df = [&](double g) { return s2 * (3 * g * g + 14 * g + 16) - 1; };
  // Start right of every root (Cauchy bound of the monic polynomial). f is increasing and convex
  // there (f'' = σ²(6γ + 14) > 0 for γ > −7/3), so Newton descends monotonically to the largest root.
  double g = 1 + std::max({7.0, std::abs(16 - 1 / s2), std::abs(12 - 1 / s2)});
  for (int it = 0; it < 200; ++it) {
    const double step = f(g) / df(g);
    g -= step;
    if (std::abs(step) <= 1e-15 * std::max(1.0, std::abs(g))) break;
  }
  return g;
}

double power_ema_beta(int64_t iteration, double gamma) {
  DOJO_CHECK(iteration >= 0, "power EMA: iteration must be >= 0, got " + std::to_string(iteration));
  return std::pow(1.0 - 1.0 / static_cast<double>(iteration + 1), gamma + 1.0);
}

void ema_update(std::vector<torch::Tensor>& ema, const std::vector<torch::Tensor>& params, double beta) {
  DOJO_CHECK(ema.size() == params.size(), "ema_update: " + std::to_string(ema.size()) + " EMA tensors for " +
                                              std::to_string(params.size()) + " parameters");
  torch::NoGradGuard no_grad;
  for (size_t i = 0; i < ema.size(); ++i) {
    DOJO_CHECK(ema[i].sizes() == params[i].sizes(),
               "ema_update: shape mismatch at parameter " + std::to_string(i));
    ema[i].mul_(beta).add_(params[i].detach().to(ema[i].options()), 1.0 - beta);
  }
}

}  // namespace dojo::diffusion
