// A load generator for `dojo serve` (and the load test): N concurrent WebSocket sessions against a
// running server for a bounded time, each in step mode (send a step, wait for its frames and
// step_done: the round trip a policy sees) or live mode (a control every 100 ms, frames as they
// come: what a teleoperator sees), or N study voters (mode study: each makes a rater, then asks for
// the next trial and votes until the time is up, a new rater when one has voted on every trial;
// a 503 is retried after a pause, as a browser would). Reports frames/s per session, latency
// percentiles, refusals, errors, the votes the server acknowledged (a SIGKILL test compares them
// with what its database holds) and the server's memory as its /metrics states it.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace dojo::serve {

struct LoadOptions {
  std::string host = "127.0.0.1";
  uint16_t port = 8080;
  std::string token;
  int sessions = 1;
  double seconds = 10;
  std::string mode = "step";  // step | live | study
  std::string model;          // "" = the server's first
  // A session also runs on past `seconds` until it has this many frames (up to a minute more):
  // the load test asserts behaviour (every session streams) whatever the machine's speed.
  int64_t min_frames = 0;
};

struct LoadReport {
  LoadOptions options;
  std::vector<double> frames_per_second;  // per session
  std::vector<int64_t> frames;            // per session
  // step: send-to-step_done round trips; live: input-to-frame latency (the echoed control clock).
  // study: the vote requests' round trips (503 answers and retries included).
  double latency_ms_p50 = 0, latency_ms_p95 = 0, latency_ms_p99 = 0;
  double server_step_ms_p50 = 0, server_step_ms_p95 = 0;  // step mode: the model step, server-side
  int64_t errors = 0;                                     // error messages the server sent
  int64_t failed_sessions = 0;       // could not connect or start, or lost the server midway
  int64_t refused_sessions = 0;      // declined at the session cap (the server answered 503)
  int64_t refusals = 0;              // study: requests answered 503 (busy), each retried
  int64_t votes_acknowledged = 0;    // study: votes answered 200 ("stored")
  int64_t answers_acknowledged = 0;  // study: their answers (one per question, a database row each)
  bool server_alive_after = true;    // /metrics answered after the run
  std::vector<std::string> failures;
  double server_rss_mib_before = 0, server_rss_mib_after = 0;
  int64_t frames_dropped = 0;  // by the server for slow clients, during the run
  nlohmann::json to_json() const;
};

// Runs the load; throws dojo::Error when the server cannot be reached at all.
LoadReport run_load(const LoadOptions& options);

}  // namespace dojo::serve
