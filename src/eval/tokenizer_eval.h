// Tokenizer evaluation: the round trip (encode, decode the posterior mean) of clips sampled from a
// dataset split, scored with the same per-frame metrics as world-model rollouts (eval/metrics.h),
// so `dojo tokenizer eval` and `dojo eval`'s tokenizer ceiling agree on the same frames.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "models/wan_vae.h"

namespace dojo::eval {

struct TokenizerEvalOptions {
  std::string split = "val";
  int clips = 16;
  int frames = 13;  // 1 + 4k
  int size = 0;     // square frames fed to the tokenizer; 0: the dataset's size
  uint64_t seed = 0;
  int keep_examples = 4;  // clips returned for a side-by-side video
};

struct TokenizerEvalResult {
  double psnr = 0, ssim = 0;  // per frame (piq), mean per clip, then over clips
  int clips = 0, frames = 0;
  std::vector<torch::Tensor> originals, reconstructions;  // [T, H, W, 3] uint8, the first examples
  nlohmann::json to_json() const;
};

TokenizerEvalResult evaluate_tokenizer(models::WanVae& vae, const std::filesystem::path& dataset,
                                       const TokenizerEvalOptions& options);

}  // namespace dojo::eval
