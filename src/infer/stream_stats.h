// Speed and memory of a stream, step by step: what `dojo wm stream`, `dojo wm speed` and the demo
// report, computed one way.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <vector>

namespace dojo::infer {

struct StreamTimings;

// The value below which a fraction q of `values` lies (nearest rank; 0 for none).
double percentile(std::vector<double> values, double q);

class StreamStats {
 public:
  // One engine step (its last_timings()) that produced `frames` video frames (4 per latent frame).
  void add(const StreamTimings& timings, int64_t frames);
  int64_t frames() const { return frames_; }
  int64_t steps() const { return static_cast<int64_t>(total_ms_.size()); }

  // {frames, frames_per_second and step_ms_p50 / p95 / max over all steps, the same as
  // steady_frames_per_second and steady_step_ms_p50 / p95 without the first two steps (allocator
  // and kernel warm-up), denoise / recache / decode_ms_mean, rss_mib_at_frame_100 (0 before 100
  // frames), rss_mib_at_end}.
  nlohmann::json summary() const;

 private:
  std::vector<double> total_ms_, denoise_ms_, recache_ms_, decode_ms_;
  std::vector<int64_t> step_frames_;
  int64_t frames_ = 0, rss_at_100_ = 0;
};

}  // namespace dojo::infer
