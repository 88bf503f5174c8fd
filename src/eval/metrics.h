// Evaluation metrics with the conventions DreamDojo reports (../shared/reference/metrics.md):
// per-frame PSNR / SSIM as in piq 0.8 (data range 1), averaged over the frames of a video, then
// over videos; and the policy-evaluation metrics Pearson r and MMRV of SimplerEnv.
//
// Frame layouts: float tensors are [N, 3, H, W] in [0, 1] (clamped); uint8 tensors are the
// [N, H, W, 3] RGB frames the video reader returns (converted as clamp(u8 / 255, 0, 1)).
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <limits>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace dojo::eval {

class Lpips;

// [N, H, W, 3] uint8 -> [N, 3, H, W] float32 in [0, 1]; float [N, 3, H, W] input is clamped to
// [0, 1] and returned as float32. Anything else throws dojo::Error.
torch::Tensor to_unit_frames(const torch::Tensor& frames);

// PSNR per frame: −10·log10(mean over C, H, W of (x − y)² + 1e-8); identical frames give 80 dB.
torch::Tensor psnr_per_frame(const torch::Tensor& pred, const torch::Tensor& gt);  // -> [N] float32

// SSIM factor of piq's automatic downsampling: max(1, round_half_even(min(H, W) / 256)).
int64_t ssim_downsample_factor(int64_t height, int64_t width);
// SSIM per frame (piq): average-pool by ssim_downsample_factor, 11 × 11 Gaussian (σ = 1.5) valid
// convolution per channel, K1 = 0.01, K2 = 0.03, mean over positions then channels. Frames must be
// at least 11 × 11 after downsampling.
torch::Tensor ssim_per_frame(const torch::Tensor& pred, const torch::Tensor& gt);  // -> [N] float32

// Mean of the per-frame values of one video; lpips is NaN when no LPIPS network was given.
struct VideoMetrics {
  double psnr = 0;
  double ssim = 0;
  double lpips = std::numeric_limits<double>::quiet_NaN();
  int64_t num_frames = 0;
};
// Frames are processed `chunk` at a time to bound memory (49 frames at 480 × 640 are ~180 MB as float).
VideoMetrics video_metrics(const torch::Tensor& pred, const torch::Tensor& gt, const Lpips* lpips = nullptr,
                           int64_t chunk = 8);
// Arithmetic mean over videos (each video weighs the same, whatever its length); lpips stays NaN
// if any video lacks it. Throws dojo::Error on an empty list.
VideoMetrics dataset_mean(const std::vector<VideoMetrics>& videos);

// SimplerEnv pearson_correlation(perf_sim, perf_real): centre both; 1 if the centred vectors are
// exactly equal, else Σ s̃r̃ / (√(Σ s̃² · Σ r̃²) + 1e-8). Sums follow numpy's pairwise order.
double pearson_correlation(const std::vector<double>& sim, const std::vector<double>& real);
// SimplerEnv mean_maximum_rank_violation(perf_sim, perf_real):
// mean_i max_j 1[(s_i > s_j) ≠ (r_i > r_j)]·|r_i − r_j| (0 when no violation). Argument order
// matters: pass (world model, real world).
double mean_maximum_rank_violation(const std::vector<double>& sim, const std::vector<double>& real);

// Spearman's rank correlation: pearson_correlation of the average ranks (ties share their mean
// rank), so it inherits the reference's exact-equality special case.
double spearman_correlation(const std::vector<double>& sim, const std::vector<double>& real);

// Per-policy success rates in the world model and in the real world (or the simulator standing
// in for it), and how well the first ranks the second.
struct PolicyRates {
  std::vector<std::string> names;
  std::vector<double> world_model, real;
};
struct PolicyAgreement {
  double pearson = 0, mmrv = 0, spearman = 0;
  double mean_abs_gap = 0;  // mean |world model - real| (world-model success tends to run high)
  nlohmann::json to_json() const;
};
PolicyAgreement policy_agreement(const PolicyRates& rates);
// Reads {"policies": [{"name": "...", "world_model": 0.8, "real": 0.7}, ...]} (rates in [0, 1], at
// least two policies). Throws dojo::Error naming the file and the field.
PolicyRates read_policy_rates(const std::filesystem::path& path);

}  // namespace dojo::eval
