#include "serve/metrics.h"

#include <unistd.h>

#include <cstdio>
#include <fstream>

namespace dojo::serve {

void ServerMetrics::observe_step(double seconds) {
  size_t bucket = 0;
  while (bucket < kLatencyBuckets.size() && seconds > kLatencyBuckets[bucket]) ++bucket;
  ++step_buckets_[bucket];
  ++step_count_;
  step_sum_us_ += static_cast<int64_t>(seconds * 1e6);
}

std::string ServerMetrics::prometheus_text() const {
  std::string out;
  const auto metric = [&](const char* name, const char* type, const char* help, int64_t value) {
    out += std::string("# HELP ") + name + " " + help + "\n# TYPE " + name + " " + type + "\n" + name + " " +
           std::to_string(value) + "\n";
  };
  metric("dojo_sessions_active", "gauge", "Live WebSocket sessions.", sessions_active_);
  metric("dojo_sessions_total", "counter", "WebSocket sessions opened.", sessions_total_);
  metric("dojo_sessions_refused_total", "counter", "Sessions refused at the concurrency cap.",
         sessions_refused_);
  metric("dojo_frames_generated_total", "counter", "Video frames generated.", frames_generated_);
  metric("dojo_frames_dropped_total", "counter", "Frames dropped for slow clients (latest frame wins).",
         frames_dropped_);
  metric("dojo_errors_total", "counter", "Requests and messages answered with an error.", errors_);
  metric("dojo_http_requests_total", "counter", "HTTP requests served.", requests_);

  out +=
      "# HELP dojo_step_seconds Wall time of one generation step (computing, not waiting for the model).\n# "
      "TYPE dojo_step_seconds histogram\n";
  int64_t cumulative = 0;
  char line[128];
  for (size_t i = 0; i < kLatencyBuckets.size(); ++i) {
    cumulative += step_buckets_[i];
    std::snprintf(line, sizeof line, "dojo_step_seconds_bucket{le=\"%g\"} %lld\n", kLatencyBuckets[i],
                  static_cast<long long>(cumulative));
    out += line;
  }
  cumulative += step_buckets_[kLatencyBuckets.size()];
  out += "dojo_step_seconds_bucket{le=\"+Inf\"} " + std::to_string(cumulative) + "\n";
  std::snprintf(line, sizeof line, "dojo_step_seconds_sum %.6f\n", step_sum_us_ / 1e6);
  out += line;
  out += "dojo_step_seconds_count " + std::to_string(step_count_.load()) + "\n";

  // The standard process metric, from /proc/self/statm (pages; the second field is resident).
  long long pages_total = 0, pages_resident = 0;
  std::ifstream statm("/proc/self/statm");
  if (statm >> pages_total >> pages_resident)
    metric("process_resident_memory_bytes", "gauge", "Resident memory size in bytes.",
           pages_resident * static_cast<int64_t>(sysconf(_SC_PAGESIZE)));
  return out;
}

}  // namespace dojo::serve
