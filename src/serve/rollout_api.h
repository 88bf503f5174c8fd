// POST /v1/rollout: a whole rollout in one request, for policies and scripts.
//   {"model": "student", "episode": "ep-3" | "image": "<base64 JPEG>", "seed": 0,
//    "actions": [[...], ...],   raw commands of the embodiment (normalised, made chunk-relative
//                               and placed in the 384-d layout here) or 384-d rows
//    "baseline": [...],         raw command at the start frame (default: the episode's first)
//    "format": "mp4" | "jpeg"}
// -> video/mp4, or {"frames": ["<base64 JPEG>", ...]} with the start frame first.
#pragma once

#include <atomic>

#include <cstdint>
#include <string>

#include "serve/metrics.h"

namespace dojo::serve {

class ModelHost;

struct HttpReply {
  int status = 200;
  std::string content_type = "application/json";
  std::string body;
};

// What one request may cost: frames are checked before any work (413 above the cap), the wall
// time between steps (503 once past it, the work done so far dropped).
struct RolloutLimits {
  int64_t max_frames = 1200;
  double max_seconds = 300;
  int jpeg_quality = 85;
  // The server's stop flag: a rollout checks it before each step and answers 503 when it is set,
  // so a stopping server waits one step for a running rollout, not its max_seconds.
  const std::atomic<bool>* stopping = nullptr;
};

// Runs the request to completion (seconds to minutes for the teacher). Bad input: a 400 reply
// whose JSON names the field; never throws.
HttpReply run_rollout_request(const ModelHost& host, const std::string& body, ServerMetrics& metrics,
                              const RolloutLimits& limits);

// Standard base64 (RFC 4648, with padding). decode throws dojo::Error naming `what` on bad input.
std::string base64_encode(std::string_view bytes);
std::string base64_decode(std::string_view text, const std::string& what);

}  // namespace dojo::serve
