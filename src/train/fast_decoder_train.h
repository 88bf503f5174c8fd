// Distils the tokenizer's Wan decoder into the fast streaming decoder (models/fast_decoder.h): on
// the tokenizer's own latents of 13-frame clips (the latent cache), the fast decoder learns the
// Wan decoder's frames (MSE in [-1, 1]). The last tenth of the clips is held out and scored as
// PSNR against Wan decoding of the same latents.
#pragma once

#include <cstdint>
#include <filesystem>
#include <vector>

#include "core/autocast.h"
#include "models/fast_decoder.h"
#include "train/latent_cache.h"

namespace dojo::train {

struct FastDecoderJob {
  std::vector<LatentCacheSpec> data;  // clips; each spec names the tokenizer
  std::filesystem::path out;          // out/checkpoint, out/loss.csv, out/latents-<i>.safetensors
  models::FastDecoderConfig model;
  int batch_size = 8;
  int64_t accumulate = 1;  // micro-batches per step and process (data_parallel.h)
  int64_t steps = 2000;
  double lr = 1e-3;  // AdamW, 50 warm-up steps, cosine to 10% over the steps
  double time_budget_s = 0;
  int64_t save_every = 500;
  uint64_t seed = 0;
  // Where it trains (the model moves there; draws stay on the CPU) and at what precision (bf16:
  // the forward pass under autocast, weights and checkpoints float32).
  torch::Device device = torch::kCPU;
  Precision precision = Precision::kFloat32;
};

struct FastDecoderResult {
  int64_t steps = 0, clips = 0, heldout_clips = 0;
  double loss = 0;          // mean of the last training losses
  double heldout_psnr = 0;  // fast vs Wan decoding of held-out latents, dB
  double seconds = 0;
};

FastDecoderResult run_fast_decoder_training(const FastDecoderJob& job);

}  // namespace dojo::train
