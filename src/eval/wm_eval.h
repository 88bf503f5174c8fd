// The paper's teacher evaluation on a dataset split: for each episode, the first ground-truth
// frame and the episode's actions drive a rollout of 1 + 12 K frames (K = 4 chunks: 49 frames,
// 3 autoregressive resets); PSNR and SSIM are taken per frame, averaged per video, then over
// videos. Two references are scored the same way: the copy-first-frame baseline (the real
// conditioning frame repeated: what a predictor that ignores the actions gets for free) and the
// tokenizer round trip of the ground truth, chunked as the rollout is (the ceiling for a rollout
// decoded by this tokenizer: every latent predicted perfectly).
#pragma once

#include <cmath>
#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "infer/world_model.h"

namespace dojo::eval {

class Lpips;

struct WmEvalOptions {
  int chunks = 4;         // 4 x 12 actions: the paper's 49-frame protocol
  int max_episodes = 16;  // evaluate at most this many episodes of the split (0: all)
  int batch = 4;          // episodes rolled out together
  infer::SamplerOptions sampler;
  infer::ConcatMode concat = infer::ConcatMode::kAligned;
  uint64_t seed = 0;
  std::filesystem::path video_dir;  // side-by-side videos (ground truth | prediction) when set
  int videos = 4;                   // how many episodes get a video
  const Lpips* lpips = nullptr;     // LPIPS as well, when the user supplied its weights
};

struct VideoScore {
  std::string episode;
  double psnr = 0, ssim = 0;            // world model
  double lpips = std::nan("");          // NaN without LPIPS weights
  double copy_psnr = 0, copy_ssim = 0;  // copy-first-frame baseline
  double copy_lpips = std::nan("");
  double recon_psnr = 0, recon_ssim = 0;  // tokenizer round trip of the ground truth
  std::string video;                      // side-by-side file, when written
};

struct WmEvalResult {
  std::string dataset, split;
  std::vector<VideoScore> videos;
  double psnr = 0, ssim = 0, copy_psnr = 0, copy_ssim = 0;  // means over videos
  double recon_psnr = 0, recon_ssim = 0;
  double lpips = std::nan(""), copy_lpips = std::nan("");
  int frames = 0;                             // per video
  double seconds = 0, frames_per_second = 0;  // generated frames / rollout time
  nlohmann::json to_json() const;
};

// The first 1 + 12 K frames of one episode with its actions, as a rollout replays them.
struct EpisodeClip {
  std::string episode;
  torch::Tensor video;    // [1 + 12 K, H, W, 3] uint8
  torch::Tensor actions;  // [12 K, 384]
  double fps = 10;
};
// `episode` names the episode by id; empty: the first episode of `split`. Throws dojo::Error
// naming the dataset when there is no such episode or it is too short.
EpisodeClip read_episode_clip(const std::filesystem::path& dataset, const std::string& split,
                              const std::string& episode, int chunks);
// Actions from a safetensors file holding "actions" [12 K, 384] (counterfactual rollouts).
torch::Tensor read_rollout_actions(const std::filesystem::path& file);

WmEvalResult evaluate_world_model(infer::WorldModel& model, const std::filesystem::path& dataset,
                                  const std::string& split, const WmEvalOptions& options);

// Markdown table of several results (one row per split).
std::string markdown_table(const std::vector<WmEvalResult>& results);

}  // namespace dojo::eval
