// One WebSocket session: the protocol, independent of the transport (server.cpp carries the
// bytes). A session runs its model on its own worker thread and hands outgoing messages to
// `send`, which must not block.
//
// Client -> server (text, JSON; one object per message):
//   {"type":"start", "mode":"live"|"step", "model":"student", "episode":"ep-3", "seed":0,
//    "image":false, "record":false}   "image": true starts from the last binary message (a JPEG
//                          upload); "record": true records the stream from its start frame on
//   {"type":"control", "velocity":[...], "t":1234.5}   live: per-dimension command velocity in the
//                          embodiment's units per second ("t": the client's clock, echoed back)
//   {"type":"command", "value":[...], "t":...}         live: an absolute command
//   {"type":"step", "actions":[[...], ...]}             step mode: one step's actions, raw commands
//                          (the embodiment's width) or rows of the model's 384-d layout
//   {"type":"reset"}       back to the start frame
//   {"type":"record", "on":true|false}                 recording (mp4 + actions + start frame +
//                          session.json); a recording from the start can be replayed (serve-check)
// Server -> client:
//   text  {"type":"ready", ...} | {"type":"step_done", ...} | {"type":"recorded", ...} |
//         {"type":"error", "message":...}   (an error never ends the session)
//   binary frames: a 32-byte little-endian header, then one JPEG:
//     "DJF1" | u32 frame sequence | u32 step | u32 step compute µs | f64 echoed client "t" | f64 server ms
#pragma once

#include <torch/torch.h>

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <string_view>
#include <thread>

#include "data/actions.h"
#include "infer/generator.h"
#include "serve/metrics.h"

namespace dojo::serve {

// A binary frame message: the 32-byte header (see the top of this file), then the JPEG.
std::string frame_message(std::string_view jpeg, uint32_t sequence, uint32_t step, uint32_t compute_us,
                          double client_t, double server_ms);
inline constexpr size_t kFrameHeaderBytes = 32;
// A message's rows of numbers ("actions": [[...], ...]) are read by data::action_rows_from_json
// (data/action_rows.h), at most 64 rows a message.

class ModelHost;
using Generator = infer::Generator;
class SessionRecorder;

struct SessionOptions {
  int jpeg_quality = 85;
  double fps = 0;  // live pacing; 0: the data's rate
  std::filesystem::path recordings = "recordings";
  size_t max_pending_steps = 8;  // step mode: queued requests beyond this get an error
};

struct Outgoing {
  bool binary = false;
  std::string data;
  bool droppable = false;  // a live frame: a slow client may lose it to a newer one
};

class Session {
 public:
  using Send = std::function<void(Outgoing)>;
  static constexpr size_t kFrameHeaderBytes = serve::kFrameHeaderBytes;

  Session(const ModelHost& host, SessionOptions options, ServerMetrics& metrics, Send send);
  ~Session();  // stops the worker; a recording in progress is finished and written
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;

  // Handle one client message. Never throws: bad input is answered with an error message.
  void on_text(std::string_view message);
  void on_binary(std::string_view message);
  // Ends the session (idempotent): the worker stops after its current step.
  void close();

 private:
  void handle(const nlohmann::json& message);
  void worker();
  void start_stream();  // on the worker: reset the generator at the start frame
  void live_step();
  // frames [n, H, W, 3]; client_t: the client clock of the input they answer (0: none)
  void send_frames(const torch::Tensor& frames, bool droppable, double client_t = 0);
  void send_text(const nlohmann::json& message);
  void error(const std::string& message);
  double now_ms() const;

  const ModelHost& host_;
  SessionOptions options_;
  ServerMetrics& metrics_;
  Send send_;
  std::chrono::steady_clock::time_point started_ = std::chrono::steady_clock::now();

  // Shared between the message handlers and the worker, under mutex_.
  std::mutex mutex_;
  std::condition_variable wake_;
  bool stop_ = false, start_requested_ = false, reset_requested_ = false;
  // Record on / off in the order asked, so an off that comes before the worker took the on still
  // ends (and reports) a recording; repeats are dropped and the list is bounded.
  std::deque<bool> record_requests_;
  void request_record(bool on);                       // under mutex_
  nlohmann::json start_;                              // the last start message
  std::string upload_;                                // the last binary upload (a JPEG)
  torch::Tensor velocity_, command_request_;          // live controls [w]
  double client_t_ = 0;                               // the client clock of the latest control
  std::deque<torch::Tensor> steps_;                   // step mode: queued action rows [n, 384 or w]
  std::string mode_;                                  // "live" | "step" of the running stream
  int64_t actions_per_step_ = 0, command_width_ = 0;  // of the running stream's model

  // The worker's own state.
  std::unique_ptr<Generator> generator_;
  std::optional<data::ActionChunker> chunker_;
  std::unique_ptr<SessionRecorder> recorder_;
  torch::Tensor start_frame_, baseline_, command_;  // [H, W, 3], [w], [w]
  torch::Tensor command_min_, command_max_;         // clamp range of live commands [w]
  std::string model_, episode_;
  uint64_t seed_ = 0;
  double frame_dt_ = 0.1;  // seconds per frame at the pacing rate
  uint32_t sequence_ = 0, step_index_ = 0;
  bool streaming_ = false;
  std::thread thread_;
};

}  // namespace dojo::serve
