#include "infer/stream_stats.h"

#include <algorithm>
#include <numeric>

#include "core/runtime.h"
#include "infer/streaming.h"

namespace dojo::infer {

namespace {

double mean(const std::vector<double>& v) {
  return v.empty() ? 0.0 : std::accumulate(v.begin(), v.end(), 0.0) / static_cast<double>(v.size());
}

double frames_per_second(const std::vector<double>& ms, const std::vector<int64_t>& frames, size_t from) {
  double seconds = 0, count = 0;
  for (size_t i = from; i < ms.size(); ++i) seconds += ms[i] / 1000, count += static_cast<double>(frames[i]);
  return seconds > 0 ? count / seconds : 0.0;
}

}  // namespace

double percentile(std::vector<double> values, double q) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  const double rank = std::min<double>(static_cast<double>(values.size() - 1), q * (values.size() - 1) + 0.5);
  return values[static_cast<size_t>(rank)];
}

void StreamStats::add(const StreamTimings& timings, int64_t frames) {
  total_ms_.push_back(timings.total_ms);
  denoise_ms_.push_back(timings.denoise_ms);
  recache_ms_.push_back(timings.recache_ms);
  decode_ms_.push_back(timings.decode_ms);
  step_frames_.push_back(frames);
  frames_ += frames;
  if (rss_at_100_ == 0 && frames_ >= 100) rss_at_100_ = resident_memory_bytes();
}

nlohmann::json StreamStats::summary() const {
  const double max_ms = total_ms_.empty() ? 0.0 : *std::max_element(total_ms_.begin(), total_ms_.end());
  const size_t warm = std::min<size_t>(2, total_ms_.size());
  const std::vector<double> steady(total_ms_.begin() + static_cast<std::ptrdiff_t>(warm), total_ms_.end());
  return {{"frames", frames_},
          {"frames_per_second", frames_per_second(total_ms_, step_frames_, 0)},
          {"steady_frames_per_second", frames_per_second(total_ms_, step_frames_, warm)},
          {"step_ms_p50", percentile(total_ms_, 0.5)},
          {"step_ms_p95", percentile(total_ms_, 0.95)},
          {"steady_step_ms_p50", percentile(steady, 0.5)},
          {"steady_step_ms_p95", percentile(steady, 0.95)},
          {"step_ms_max", max_ms},
          {"denoise_ms_mean", mean(denoise_ms_)},
          {"recache_ms_mean", mean(recache_ms_)},
          {"decode_ms_mean", mean(decode_ms_)},
          {"rss_mib_at_frame_100", rss_at_100_ / 1048576.0},
          {"rss_mib_at_end", resident_memory_bytes() / 1048576.0}};
}

}  // namespace dojo::infer
