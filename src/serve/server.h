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
// Binds 127.0.0.1 unless told otherwise; with a token every route but /health needs it (an
// "Authorization: Bearer" header, or ?token= where browsers cannot set headers).
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
  uint16_t port = 8080;                // 0: any free port (tests)
  std::string token;                   // empty: open
  int max_sessions = 4;                // concurrent WebSocket sessions and rollout jobs; more get 503
  size_t max_message_bytes = 4 << 20;  // WebSocket messages and request bodies
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
