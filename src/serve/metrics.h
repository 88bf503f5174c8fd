// The server's counters in the Prometheus text format (GET /metrics): sessions, frames, errors,
// dropped frames and a histogram of step latency. Every field is atomic: sessions update it from
// their own threads while /metrics reads it.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <string>

namespace dojo::serve {

class ServerMetrics {
 public:
  // Upper bounds of the step latency histogram, in seconds (Prometheus "le" labels).
  static constexpr std::array<double, 10> kLatencyBuckets = {0.01, 0.025, 0.05, 0.1, 0.2,
                                                             0.4,  0.8,   1.6,  3.2, 6.4};

  void session_opened() { ++sessions_active_, ++sessions_total_; }
  void session_closed() { --sessions_active_; }
  void session_refused() { ++sessions_refused_; }
  void frames_generated(int64_t n) { frames_generated_ += n; }
  void frames_dropped(int64_t n) { frames_dropped_ += n; }
  void error() { ++errors_; }
  void request() { ++requests_; }
  void observe_step(double seconds);

  int64_t sessions_active() const { return sessions_active_; }
  int64_t frames_dropped() const { return frames_dropped_; }
  int64_t errors() const { return errors_; }
  std::string prometheus_text() const;

 private:
  std::atomic<int64_t> sessions_active_{0}, sessions_total_{0}, sessions_refused_{0};
  std::atomic<int64_t> frames_generated_{0}, frames_dropped_{0}, errors_{0}, requests_{0};
  std::array<std::atomic<int64_t>, kLatencyBuckets.size() + 1> step_buckets_{};  // last: +Inf
  std::atomic<int64_t> step_count_{0};
  std::atomic<int64_t> step_sum_us_{0};
};

}  // namespace dojo::serve
