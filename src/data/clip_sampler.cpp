#include "data/clip_sampler.h"

#include "core/error.h"

namespace dojo::data {

ClipWindow make_window(int64_t start, int stride, int num_frames) {
  ClipWindow window;
  window.start = start;
  window.stride = stride;
  for (int i = 0; i <= num_frames; ++i) window.steps.push_back(start + static_cast<int64_t>(i) * stride);
  return window;
}

bool window_fits(int64_t episode_frames, int stride, int num_frames) {
  return stride > 0 && static_cast<int64_t>(num_frames) * stride < episode_frames;
}

uint64_t uniform_index(std::mt19937_64& rng, uint64_t n) {
  DOJO_CHECK(n > 0, "uniform_index needs n > 0");
  // Rejection sampling removes the modulo bias of a plain `rng() % n`.
  const uint64_t limit = UINT64_MAX - UINT64_MAX % n;
  uint64_t x;
  do {
    x = rng();
  } while (x >= limit);
  return x % n;
}

std::optional<ClipWindow> sample_window(int64_t episode_frames, const ClipConfig& config,
                                        std::mt19937_64& rng) {
  std::vector<int> feasible;
  for (int stride : config.strides)
    if (window_fits(episode_frames, stride, config.num_frames)) feasible.push_back(stride);
  if (feasible.empty()) return std::nullopt;
  const int stride = feasible[uniform_index(rng, feasible.size())];
  // The last step is start + num_frames * stride and must be a valid frame index.
  const int64_t starts = episode_frames - static_cast<int64_t>(config.num_frames) * stride;
  const int64_t start = static_cast<int64_t>(uniform_index(rng, static_cast<uint64_t>(starts)));
  return make_window(start, stride, config.num_frames);
}

std::vector<ClipWindow> all_windows(int64_t episode_frames, int stride, int num_frames, int64_t hop) {
  DOJO_CHECK(hop > 0, "window hop must be positive");
  std::vector<ClipWindow> windows;
  for (int64_t start = 0; start + static_cast<int64_t>(num_frames) * stride < episode_frames; start += hop)
    windows.push_back(make_window(start, stride, num_frames));
  return windows;
}

}  // namespace dojo::data
