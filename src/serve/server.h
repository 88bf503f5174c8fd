// `dojo serve`: one HTTP + WebSocket server (Boost.Beast on Asio) for live teleoperation in the
// browser, the policy-facing rollout API and the preference study.
//
//   GET  /health            200 {"status": "ok"}, 503 while the models load
//   GET  /metrics           Prometheus text (serve/metrics.h)
//   GET  /api/capabilities  models, embodiments, action layout, start episodes
//   GET  /                  the teleoperation page (embedded in the binary)
//   POST /v1/rollout        start frame + actions -> mp4 (serve/rollout_api.h)
//   GET  /ws                WebSocket sessions: live teleop or step-by-step (serve/session.h)
//   GET  /study             the preference study page, with --study (serve/study_api.h)
//
// Binds 127.0.0.1 unless told otherwise (another host needs a token, or `insecure`); with a token
// every route but /health and the pages needs it, as an "Authorization: Bearer" header or the
// dojo_token cookie the pages set from the address's #token= fragment, never in a URL.
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>

#include "serve/metrics.h"

namespace dojo::serve {

class ModelHost;

struct ServeOptions {
  std::string host = "127.0.0.1";
  uint16_t port = 8080;  // 0: any free port (tests)
  // Empty: open. Otherwise every call but the pages needs it, as an "Authorization: Bearer" header
  // or the dojo_token cookie the pages set from the address's #token= fragment; never in the URL
  // (addresses end up in logs and browser history). Compared in constant time.
  std::string token;
  // A host other than loopback without a token is refused unless this is set (--insecure).
  bool insecure = false;
  int max_sessions = 4;                // concurrent WebSocket sessions and rollout jobs; more get 503
  size_t max_message_bytes = 4 << 20;  // WebSocket messages and request bodies
  int64_t max_rollout_frames = 1200;   // frames one POST /v1/rollout may ask for; more get 413
  double max_rollout_seconds = 300;    // a rollout still generating after this stops with 503
  int study_threads = 4;               // the study's requests (a vote waits for its fsync) run on this pool
  int max_study_requests = 256;        // study requests queued or running; more get 503
  int jpeg_quality = 85;
  double fps = 0;  // live pacing in frames/s; 0: the data's rate (10 for DojoSim)
  std::filesystem::path recordings = "recordings";
  int io_threads = 2;
  std::filesystem::path study;
  std::filesystem::path tls_cert, tls_key;  // PEM files: serve HTTPS / WSS instead of HTTP / WS  // a study
                                            // directory (serve/study.h): serves /study and its API
};

class Server {
 public:
  Server(ServeOptions options, std::shared_ptr<ModelHost> host);
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  // Binds and starts serving on background threads; returns the bound port. Throws dojo::Error
  // when the address cannot be bound.
  uint16_t start();
  // Stops accepting, ends every session (recordings are finished and written) and joins.
  void stop();
  ServerMetrics& metrics();

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace dojo::serve
