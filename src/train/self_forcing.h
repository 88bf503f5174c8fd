// Self-Forcing with distribution matching (DMD): the warmed-up student rolls out its own context
// through the KV cache, and its last frames are pulled toward the teacher's distribution by the
// difference of two scores: the frozen teacher (real) and a critic trained by flow matching on the
// student's own samples (fake). Facts: ../shared/reference/self_forcing.md §3.
//
// One iteration (self_forcing.md §3.3-§3.7):
//   draw the exit hop n ∈ {1..4} and the rollout length end ∈ [min_frames, max_frames] latents
//   roll the student out from the clip's first latent: each new frame takes n hops, only the last
//   one with gradient and only for the last `loss_frames` frames; a clean pass without gradient
//   writes each frame into the cache
//   window = [the frame before the last loss_frames (conditioning), the last loss_frames]
//   generator step (every (critic_steps + 1)-th iteration): x_D = (1 − σ)·G + σ·ε, σ from the
//     shifted uniform; g = (x̂0_fake − x̂0_real) / mean|G − x̂0_real|; loss mean((G − sg(G − g))²)
//   critic step (otherwise): flow matching of the critic on the detached rollout
// Differences from the release, for a CPU-sized setting: the conditioning frame of the score
// window is the student's latent itself (the release decodes and re-encodes it), and the scores
// see it with the frame-replace conditioning the teacher was trained with (the release feeds it
// at σ ≈ 1e-4).
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <vector>

#include "infer/streaming.h"
#include "models/dit.h"

namespace dojo::train {

struct SelfForcingOptions {
  double generator_lr = 1e-5;  // released 1e-7 for the 2B net
  double critic_lr = 1e-4;     // released 1e-5
  double weight_decay = 0.01;
  double grad_clip = 1.0;
  int critic_steps = 4;     // critic updates per generator update (released 1 : 4)
  int64_t min_frames = 4;   // rollout length in latent frames, drawn per iteration
  int64_t max_frames = 13;  // (released: 4 ... 13, i.e. 13 ... 49 video frames)
  int64_t loss_frames = 3;  // frames generated with gradient and scored
  double shift = 5.0;       // σ = shift·u / (1 + (shift − 1)·u) for the score times
  // Share of each batch's rollouts driven by another clip's actions from the clip's first frame
  // (teacher and critic score them with those actions): counterfactual motions the recorded data
  // pairs with no first frame, so a student that ignores the actions' direction is pulled back.
  double counterfactual_share = 0;
  nlohmann::json to_json() const;
};

// The student's own rollout for training. first: [B, 16, 1, h, w] clean latent, actions
// [B, 4 (frames − 1), 384], noise [B, 16, frames, h, w] (one ε per frame, kept across hops).
// Each new frame runs `exit_hop` + 1 hops of the student schedule; frames >= grad_from keep the
// gradient of their last hop. Returns [B, 16, frames, h, w], frame 0 = first.
torch::Tensor student_rollout(models::ActionDitImpl& student, const infer::StudentConfig& config,
                              const torch::Tensor& first, const torch::Tensor& actions,
                              const torch::Tensor& noise, int exit_hop, int64_t grad_from);

// Losses on a score window: window [B, 16, 1 + L, h, w] (frame 0 conditioning), actions
// [B, 4 L, 384], sigma [B], noise like window.
// DMD generator loss (the window carries the student's gradient; teacher and critic run without).
torch::Tensor dmd_generator_loss(models::ActionDitImpl& teacher, models::ActionDitImpl& critic,
                                 const torch::Tensor& window, const torch::Tensor& actions,
                                 const torch::Tensor& sigma, const torch::Tensor& noise);
// Flow-matching loss of the critic on the (detached) window.
torch::Tensor critic_loss(models::ActionDitImpl& critic, const torch::Tensor& window,
                          const torch::Tensor& actions, const torch::Tensor& sigma,
                          const torch::Tensor& noise);

}  // namespace dojo::train
