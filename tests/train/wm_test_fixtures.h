// Shared fixtures of the world-model trainer tests: a DiT small enough for unit tests (the
// structure and every code path are the real ones) and latents whose motion the actions explain.
#pragma once

#include <ATen/CPUGeneratorImpl.h>
#include <torch/torch.h>

#include <cstdint>

#include "models/dit.h"

namespace dojo::train::test_fixtures {

// live_actions: fc2 of the action MLPs drawn instead of zero-initialised, so the actions matter
// from the first step. width: model channels, a multiple of 32 (one block and one head per 32).
inline models::DitConfig tiny_dit(bool live_actions = false, int64_t width = 64) {
  auto c = models::DitConfig::small();
  c.model_channels = width;
  c.num_blocks = width / 32;
  c.num_heads = width / 32;
  c.adaln_lora_dim = width / 4;
  c.action_hidden_dim = width;
  c.crossattn_emb_channels = width / 4;
  c.crossattn_proj_dim = width / 4;
  if (live_actions) c.zero_init_action_fc2 = false;
  return c;
}

inline torch::Generator gen(uint64_t seed) { return at::make_generator<at::CPUGeneratorImpl>(seed); }

// Latent "videos" whose frames move by the actions: frame t = frame 0 shifted by the sum of the
// first (t * 4) action values of slot 169 (one channel offset per latent frame).
inline void action_driven_latents(int64_t n, torch::Tensor& x0, torch::Tensor& actions, uint64_t seed) {
  auto g = gen(seed);
  x0 = torch::randn({n, 16, 4, 4, 4}, g) * 0.5;  // [n, 16, 4, 4, 4]
  actions = torch::zeros({n, 12, 384});
  actions.select(2, 169).copy_(torch::rand({n, 12}, g) * 2 - 1);
  for (int64_t t = 1; t < 4; ++t) {
    const auto shift = actions.select(2, 169).narrow(1, 0, 4 * t).sum(1);  // [n]
    x0.select(2, t).copy_(x0.select(2, 0) + shift.view({n, 1, 1, 1}));
  }
}

}  // namespace dojo::train::test_fixtures
