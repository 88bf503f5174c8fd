#include "train/self_forcing.h"

#include <cmath>

#include "core/autocast.h"
#include "core/error.h"

namespace dojo::train {

nlohmann::json SelfForcingOptions::to_json() const {
  nlohmann::json j = {
      {"generator_lr", generator_lr}, {"critic_lr", critic_lr},       {"weight_decay", weight_decay},
      {"grad_clip", grad_clip},       {"critic_steps", critic_steps}, {"min_frames", min_frames},
      {"max_frames", max_frames},     {"loss_frames", loss_frames},   {"shift", shift}};
  if (counterfactual_share > 0) j["counterfactual_share"] = counterfactual_share;
  return j;
}

torch::Tensor student_rollout(models::ActionDitImpl& student, const infer::StudentConfig& config,
                              const torch::Tensor& first, const torch::Tensor& actions,
                              const torch::Tensor& noise, int exit_hop, int64_t grad_from) {
  const auto schedule = config.schedule();
  DOJO_CHECK(exit_hop >= 0 && exit_hop < static_cast<int>(schedule.size()),
             "self-forcing: exit hop out of range");
  const int64_t frames = noise.size(2), k = student.config.actions_per_latent_frame;
  DOJO_CHECK(actions.size(1) == k * (frames - 1), "self-forcing: actions must cover every new frame");
  const auto& c = student.config;
  const int64_t tokens = (first.size(3) / c.patch_spatial) * (first.size(4) / c.patch_spatial);
  const int64_t window = config.window_frames, sink = config.sink_frames;
  DOJO_CHECK(sink >= 0 && sink <= window, "self-forcing: the attention sink must fit in the window");
  std::vector<models::DitKvCache> cache(static_cast<size_t>(c.num_blocks));
  for (auto& e : cache) e.set_sink(sink * tokens);
  const auto zeros_mask = torch::zeros_like(first.narrow(1, 0, 1));  // [B, 1, 1, h, w]

  // The clean pass that writes a frame's keys and values (no gradient, as released).
  const auto recache = [&](const torch::Tensor& x0, int64_t f) {
    torch::NoGradGuard no_grad;
    models::DitInputs in;
    in.x = x0.detach();
    in.timesteps = torch::zeros({x0.size(0), 1}, x0.options());
    in.condition_mask = zeros_mask;
    if (f > 0) in.actions = actions.narrow(1, k * (f - 1), k);
    in.frame_offset = f;
    in.kv_cache = &cache;
    in.store_kv = true;
    student.forward(in);
    for (auto& e : cache) e.keep_last((window - sink) * tokens);  // and the sink
  };
  std::vector<torch::Tensor> out = {first};
  recache(first, 0);
  for (int64_t f = 1; f < frames; ++f) {
    if (sink > 0 && config.sink_position == infer::SinkPosition::kWindowEdge && f > window) {
      // As in streaming: the sink takes the position of frame f - window.
      const auto [cos, sin] = models::temporal_rope_shift(student, f - window);
      for (auto& e : cache) e.place_sink(cos, sin);
    }
    models::DitInputs base;
    base.actions = actions.narrow(1, k * (f - 1), k);
    base.condition_mask = zeros_mask;
    base.frame_offset = f;
    base.kv_cache = &cache;
    base.store_kv = false;
    const auto eps = noise.narrow(2, f, 1);  // [B, 16, 1, h, w]
    auto x = eps;
    torch::Tensor x0;
    for (int s = 0; s <= exit_hop; ++s) {
      const bool grad = s == exit_hop && f >= grad_from && torch::GradMode::is_enabled();
      // Under autocast the passes without gradients cached bf16 copies of the weights that carry
      // no graph; the pass that trains must cast them afresh.
      if (grad) AutocastGuard::clear_cache();
      torch::AutoGradMode mode(grad);
      x0 = infer::student_x0(student, base, x, schedule[static_cast<size_t>(s)]);
      if (s < exit_hop) {
        const double t = schedule[static_cast<size_t>(s + 1)].trigflow_t;
        x = (x0 * std::cos(t) + eps * std::sin(t)).detach();
      }
    }
    out.push_back(x0);
    if (f + 1 < frames) recache(x0, f);
  }
  return torch::cat(out, 2);  // [B, 16, frames, h, w]
}

namespace {

// x̂0 of a score network on the noised window, with frame 0 given as conditioning.
torch::Tensor score_x0(models::ActionDitImpl& net, const torch::Tensor& window, const torch::Tensor& x_noisy,
                       const torch::Tensor& actions, const torch::Tensor& sigma, const torch::Tensor& noise) {
  auto mask = torch::zeros_like(window.narrow(1, 0, 1));  // [B, 1, T, h, w]
  mask.narrow(2, 0, 1).fill_(1);
  models::DitInputs in;
  in.timesteps = (sigma * 1000).unsqueeze(1);  // [B, 1]
  in.actions = actions;
  const auto v = models::denoise_velocity(net, in, x_noisy, window, noise, mask);
  return x_noisy - sigma.view({-1, 1, 1, 1, 1}) * v;
}

torch::Tensor noised(const torch::Tensor& window, const torch::Tensor& sigma, const torch::Tensor& noise) {
  const auto s = sigma.view({-1, 1, 1, 1, 1});
  return (1 - s) * window + s * noise;
}

}  // namespace

torch::Tensor dmd_generator_loss(models::ActionDitImpl& teacher, models::ActionDitImpl& critic,
                                 const torch::Tensor& window, const torch::Tensor& actions,
                                 const torch::Tensor& sigma, const torch::Tensor& noise) {
  const int64_t L = window.size(2) - 1;
  torch::Tensor g;
  {
    torch::NoGradGuard no_grad;
    const auto w = window.detach();
    const auto x = noised(w, sigma, noise);
    const auto real = score_x0(teacher, w, x, actions, sigma, noise).narrow(2, 1, L);
    const auto fake = score_x0(critic, w, x, actions, sigma, noise).narrow(2, 1, L);
    // The per-sample normaliser keeps the step size independent of how far off the sample is.
    const auto norm = (w.narrow(2, 1, L) - real).abs().mean({1, 2, 3, 4}, /*keepdim=*/true).clamp_min(1e-5);
    g = (fake - real) / norm;  // [B, 16, L, h, w]
  }
  const auto generated = window.narrow(2, 1, L);
  // d/dG of mean((G − sg(G − g))²) is 2g/N: the score difference, pushed through G's graph.
  return (generated - (generated - g).detach()).pow(2).mean();
}

torch::Tensor critic_loss(models::ActionDitImpl& critic, const torch::Tensor& window,
                          const torch::Tensor& actions, const torch::Tensor& sigma,
                          const torch::Tensor& noise) {
  const int64_t L = window.size(2) - 1;
  const auto w = window.detach();
  const auto x = noised(w, sigma, noise);
  auto mask = torch::zeros_like(w.narrow(1, 0, 1));
  mask.narrow(2, 0, 1).fill_(1);
  models::DitInputs in;
  in.timesteps = (sigma * 1000).unsqueeze(1);
  in.actions = actions;
  const auto v = models::denoise_velocity(critic, in, x, w, noise, mask);  // [B, 16, 1 + L, h, w]
  // |v̂ − v|² = |x0 − x̂0|² / σ² in rectified-flow units; the release's TrigFlow form weights it by a
  // further 1 / (cos t + sin t)² (1 to 1/2 over t), which only reweights the noise levels.
  return (v - (noise - w)).narrow(2, 1, L).pow(2).mean();
}

}  // namespace dojo::train
