#include "serve/session.h"

#include "data/action_rows.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/log.h"
#include "io/jpeg.h"
#include "io/video.h"
#include "serve/model_host.h"

namespace dojo::serve {

std::string frame_message(std::string_view jpeg, uint32_t sequence, uint32_t step, uint32_t compute_us,
                          double client_t, double server_ms) {
  std::string message(kFrameHeaderBytes, '\0');
  std::memcpy(message.data(), "DJF1", 4);
  std::memcpy(message.data() + 4, &sequence, 4);  // little-endian hosts (x86-64, arm64)
  std::memcpy(message.data() + 8, &step, 4);
  std::memcpy(message.data() + 12, &compute_us, 4);
  std::memcpy(message.data() + 16, &client_t, 8);
  std::memcpy(message.data() + 24, &server_ms, 8);
  message.append(jpeg);
  return message;
}

namespace fs = std::filesystem;

// A session's recording: the frames as they are sent (an mp4), every step's actions as JSON lines
// and the start frame, written into a hidden directory that is renamed into place when it is
// complete, so a recordings folder never holds half a recording under a real name.
class SessionRecorder {
 public:
  // `about`: what a replay of the recording needs (session.json: model, episode, dataset, first step).
  SessionRecorder(const fs::path& root, const std::string& name, const torch::Tensor& start, double fps,
                  const nlohmann::json& about)
      : partial_(root / ("." + name + ".partial")), final_(root / name) {
    fs::create_directories(partial_);
    write_file_atomic(partial_ / "start.jpg", io::encode_jpeg(start, 95));
    write_file_atomic(partial_ / "session.json", about.dump(2) + "\n");
    io::VideoWriterOptions w;
    w.fps = fps;
    video_ = std::make_unique<io::VideoWriter>((partial_ / "video.mp4").string(), w);
    video_->write(start);
    actions_.open(partial_ / "actions.jsonl");
    DOJO_CHECK(actions_.good(), (partial_ / "actions.jsonl").string() + ": cannot write");
  }
  void add(const torch::Tensor& raw, const torch::Tensor& layout, const torch::Tensor& frames) {
    nlohmann::json line = {{"actions", tensor_rows(layout)}};
    if (raw.defined()) line["raw"] = tensor_rows(raw);
    actions_ << line.dump() << "\n";
    video_->write_many(frames);
  }
  // Closes the files and moves the directory into place. Returns where it went.
  fs::path finish() {
    actions_.close();
    video_->close();
    fsync_directory(partial_);
    fs::rename(partial_, final_);
    fsync_directory(final_.parent_path());
    return final_;
  }
  int64_t frames() const { return video_->frames_written(); }

 private:
  static nlohmann::json tensor_rows(const torch::Tensor& rows) {  // [n, w] -> [[...], ...]
    const auto c = rows.to(torch::kFloat).contiguous();
    nlohmann::json out = nlohmann::json::array();
    for (int64_t i = 0; i < c.size(0); ++i)
      out.push_back(std::vector<float>(c[i].data_ptr<float>(), c[i].data_ptr<float>() + c.size(1)));
    return out;
  }
  fs::path partial_, final_;
  std::unique_ptr<io::VideoWriter> video_;
  std::ofstream actions_;
};

namespace {

torch::Tensor json_vector(const nlohmann::json& v, int64_t width, const std::string& where) {  // -> [w]
  DOJO_CHECK(v.is_array() && static_cast<int64_t>(v.size()) == width,
             where + " must be an array of " + std::to_string(width) + " numbers");
  return data::action_rows_from_json(nlohmann::json::array({v}), where, 64)[0];
}

}  // namespace

Session::Session(const ModelHost& host, SessionOptions options, ServerMetrics& metrics, Send send)
    : host_(host), options_(std::move(options)), metrics_(metrics), send_(std::move(send)) {
  thread_ = std::thread([this] { worker(); });
}

Session::~Session() {
  close();
  if (thread_.joinable()) thread_.join();
}

void Session::close() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  wake_.notify_all();
}

double Session::now_ms() const {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - started_).count();
}

void Session::send_text(const nlohmann::json& message) { send_(Outgoing{false, message.dump(), false}); }

void Session::error(const std::string& message) {
  metrics_.error();
  send_text({{"type", "error"}, {"message", message}});
}

void Session::on_binary(std::string_view message) {
  std::lock_guard<std::mutex> lock(mutex_);
  upload_.assign(message.data(), message.size());  // a start image, used by the next start
}

void Session::on_text(std::string_view text) {
  try {
    const auto message = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
    DOJO_CHECK(!message.is_discarded(), "message is not valid JSON");
    DOJO_CHECK(message.is_object() && message.contains("type") && message["type"].is_string(),
               "message must be a JSON object with a string 'type'");
    handle(message);
  } catch (const std::exception& e) {
    error(e.what());
  }
}

void Session::handle(const nlohmann::json& m) {
  const auto type = m["type"].get<std::string>();
  std::unique_lock<std::mutex> lock(mutex_);
  if (type == "start") {
    const auto mode = m.value("mode", std::string("live"));
    DOJO_CHECK(mode == "live" || mode == "step", "start: 'mode' must be \"live\" or \"step\"");
    DOJO_CHECK(!m.contains("model") || m["model"].is_string(), "start: 'model' must be a string");
    DOJO_CHECK(!m.contains("episode") || m["episode"].is_string(), "start: 'episode' must be a string");
    DOJO_CHECK(!m.contains("seed") || m["seed"].is_number_unsigned(),
               "start: 'seed' must be a non-negative integer");
    DOJO_CHECK(!m.value("image", false) || !upload_.empty(),
               "start: 'image' needs a JPEG sent first as a binary message");
    DOJO_CHECK(!m.contains("record") || m["record"].is_boolean(), "start: 'record' must be true or false");
    start_ = m;
    start_requested_ = true;
    steps_.clear();
    if (m.value("record", false)) request_record(true);  // from the start frame on
  } else if (type == "control" || type == "command") {
    DOJO_CHECK(streaming_ && !start_requested_, type + ": start a session and wait for 'ready' first");
    const auto& key = type == "control" ? "velocity" : "value";
    DOJO_CHECK(m.contains(key), type + ": missing '" + key + "'");
    DOJO_CHECK(command_width_ > 0,
               type + ": this model takes no raw commands; use step mode with 384-d rows");
    const auto v = json_vector(m[key], command_width_, type + "." + key);
    if (type == "control")
      velocity_ = v;
    else
      command_request_ = v;
    if (m.contains("t") && m["t"].is_number()) client_t_ = m["t"].get<double>();
  } else if (type == "step") {
    DOJO_CHECK(mode_ == "step" && streaming_ && !start_requested_,
               "step: start a session with \"mode\": \"step\" and wait for 'ready' first");
    DOJO_CHECK(steps_.size() < options_.max_pending_steps, "step: more than " +
                                                               std::to_string(options_.max_pending_steps) +
                                                               " steps pending; wait for step_done");
    DOJO_CHECK(m.contains("actions"), "step: missing 'actions'");
    const auto rows = data::action_rows_from_json(m["actions"], "step.actions", 64);
    DOJO_CHECK(rows.size(0) == actions_per_step_,
               "step.actions: this model takes " + std::to_string(actions_per_step_) +
                   " actions per step, got " + std::to_string(rows.size(0)));
    DOJO_CHECK(
        rows.size(1) == data::kUnifiedActionDim || (command_width_ > 0 && rows.size(1) == command_width_),
        "step.actions: rows must have " + std::to_string(data::kUnifiedActionDim) + " values" +
            (command_width_ > 0 ? " or " + std::to_string(command_width_) + " (raw commands)" : ""));
    steps_.push_back(rows);
  } else if (type == "reset") {
    DOJO_CHECK(streaming_ || start_requested_, "reset: start a session first");
    reset_requested_ = true;
  } else if (type == "record") {
    DOJO_CHECK(m.contains("on") && m["on"].is_boolean(), "record: 'on' must be true or false");
    request_record(m["on"].get<bool>());
  } else {
    throw Error("unknown message type '" + type + "'");
  }
  lock.unlock();
  wake_.notify_all();
}

void Session::send_frames(const torch::Tensor& frames, bool droppable, double client_t) {
  // The step's model compute in microseconds: live clients see server-side step time per frame.
  const auto compute_us =
      static_cast<uint32_t>(generator_ ? std::min(generator_->last_step_seconds() * 1e6, 4.0e9) : 0.0);
  for (int64_t i = 0; i < frames.size(0); ++i) {
    send_(Outgoing{true,
                   frame_message(io::encode_jpeg(frames[i], options_.jpeg_quality), sequence_++, step_index_,
                                 compute_us, client_t, now_ms()),
                   droppable});
  }
  metrics_.frames_generated(frames.size(0));
}

void Session::start_stream() {
  nlohmann::json start;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    start = start_;
  }
  const auto model = start.value("model", std::string());
  generator_ = host_.make_generator(model);
  chunker_ = host_.chunker(model);
  const auto stats = host_.command_stats(model);
  command_min_ = stats ? torch::tensor(stats->min) : torch::Tensor();
  command_max_ = stats ? torch::tensor(stats->max) : torch::Tensor();
  if (start.value("image", false)) {
    std::string upload;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      upload = upload_;
    }
    start_frame_ = host_.fit_image(model, io::decode_jpeg(upload, "start image"));
    baseline_ = torch::Tensor();
    episode_.clear();
  } else {
    const auto s = host_.start_frame(model, start.value("episode", std::string()));
    start_frame_ = s.frame;
    baseline_ = s.baseline;
    episode_ = s.episode;
  }
  if (command_min_.defined() && (!baseline_.defined() || baseline_.size(0) != command_min_.size(0)))
    baseline_ = (command_min_ + command_max_) / 2;  // an image: start from the middle of the range
  model_ = host_.resolve(model);
  seed_ = start.value("seed", uint64_t{0});
  std::lock_guard<std::mutex> lock(mutex_);
  mode_ = start.value("mode", std::string("live"));
  actions_per_step_ = generator_->actions_per_step();
  command_width_ = command_min_.defined() ? command_min_.size(0) : 0;
  const double fps = options_.fps > 0 ? options_.fps : 10.0;
  frame_dt_ = 1.0 / fps;
}

void Session::request_record(bool on) {
  constexpr size_t kMaxPending = 8;
  if (!record_requests_.empty() && record_requests_.back() == on) return;
  // Full (a client toggling faster than the steps run): the last request is taken back instead,
  // which leaves the newest wish at the end.
  if (record_requests_.size() >= kMaxPending)
    record_requests_.pop_back();
  else
    record_requests_.push_back(on);
}

void Session::worker() {
  auto next_due = std::chrono::steady_clock::now();
  while (true) {
    bool start = false, reset = false;
    std::deque<bool> records;
    torch::Tensor step_rows;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      const auto requested = [&] {
        return stop_ || start_requested_ || reset_requested_ || !record_requests_.empty() || !steps_.empty();
      };
      // Only a live stream has a clock to keep; otherwise sleep until a message wakes the worker.
      if (streaming_ && mode_ == "live")
        wake_.wait_until(lock, next_due, requested);
      else
        wake_.wait(lock, requested);
      if (stop_) break;
      start = std::exchange(start_requested_, false);
      reset = std::exchange(reset_requested_, false);
      records.swap(record_requests_);
      if (!start && !steps_.empty()) {
        step_rows = steps_.front();
        steps_.pop_front();
      }
    }
    try {
      if (start) {
        {
          std::lock_guard<std::mutex> lock(mutex_);
          streaming_ = false;
        }
        start_stream();
        reset = true;
      }
      if (reset && generator_) {
        const auto first = generator_->reset(start_frame_, seed_);  // [n, H, W, 3]
        if (chunker_) {
          chunker_->reset();
          if (baseline_.defined()) chunker_->set_baseline(baseline_);
        }
        command_ = baseline_.defined() ? baseline_.clone() : torch::Tensor();
        {
          std::lock_guard<std::mutex> lock(mutex_);
          velocity_ = command_request_ = torch::Tensor();
          streaming_ = true;
        }
        step_index_ = 0;
        if (recorder_) {  // a recording covers one stream: a reset ends it (before 'ready', so the
                          // start frame follows 'ready' directly)
          const auto where = recorder_->finish();
          recorder_.reset();
          send_text({{"type", "recorded"}, {"path", where.string()}});
        }
        send_text({{"type", "ready"},
                   {"model", model_},
                   {"mode", mode_},
                   {"episode", episode_},
                   {"width", start_frame_.size(1)},
                   {"height", start_frame_.size(0)},
                   {"actions_per_step", generator_->actions_per_step()},
                   {"fps", 1.0 / frame_dt_},
                   {"command", command_.defined() ? nlohmann::json(std::vector<float>(
                                                        command_.data_ptr<float>(),
                                                        command_.data_ptr<float>() + command_.numel()))
                                                  : nlohmann::json()}});
        send_frames(first, false);
        next_due = std::chrono::steady_clock::now();
      }
      for (const bool record : records) {
        if (record && !recorder_ && generator_) {
          const auto name =
              "session-" + std::to_string(std::chrono::system_clock::now().time_since_epoch().count());
          fs::create_directories(options_.recordings);
          // first_step 0: the video starts at the start frame and every step's commands are in it, so
          // the session can be replayed (dojo serve-check); later, the steps before it are missing.
          const nlohmann::json about = {{"model", model_},        {"mode", mode_},
                                        {"episode", episode_},    {"data", host_.data_dir().string()},
                                        {"split", host_.split()}, {"seed", seed_},
                                        {"fps", 1.0 / frame_dt_}, {"first_step", step_index_}};
          recorder_ = std::make_unique<SessionRecorder>(options_.recordings, name, start_frame_,
                                                        1.0 / frame_dt_, about);
          send_text({{"type", "recording"}, {"name", name}});
        } else if (!record && recorder_) {
          const auto where = recorder_->finish();
          recorder_.reset();
          send_text({{"type", "recorded"}, {"path", where.string()}});
        }
      }
      if (step_rows.defined() && generator_) {
        torch::Tensor raw, layout = step_rows;
        if (step_rows.size(1) != data::kUnifiedActionDim) {
          DOJO_CHECK(chunker_, "step: this model takes 384-d rows");
          raw = step_rows;
          layout = chunker_->push(step_rows);
        }
        const auto t0 = std::chrono::steady_clock::now();
        const auto frames = generator_->step(layout);  // [n, H, W, 3]
        const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        metrics_.observe_step(generator_->last_step_seconds());
        ++step_index_;
        if (recorder_) recorder_->add(raw, layout, frames);
        send_frames(frames, false);
        send_text(
            {{"type", "step_done"},
             {"step", step_index_},
             {"frames", frames.size(0)},
             {"ms", generator_->last_step_seconds() * 1000},                       // computing
             {"queued_ms", (seconds - generator_->last_step_seconds()) * 1000}});  // other sessions' turns
      }
      bool live = false;
      {
        std::lock_guard<std::mutex> lock(mutex_);
        live = streaming_ && mode_ == "live";
      }
      if (live && std::chrono::steady_clock::now() >= next_due) {
        live_step();
        next_due += std::chrono::duration_cast<std::chrono::steady_clock::duration>(
            std::chrono::duration<double>(frame_dt_ * generator_->actions_per_step()));
        // A step slower than real time does not build a backlog: the next is due now.
        next_due = std::max(next_due, std::chrono::steady_clock::now());
      }
    } catch (const std::exception& e) {
      error(e.what());
      std::lock_guard<std::mutex> lock(mutex_);
      if (!generator_) streaming_ = false;
    }
  }
  if (recorder_) {
    try {
      recorder_->finish();
    } catch (const std::exception& e) {
      LOG_WARN("serve: recording not finished: ", e.what());
    }
  }
}

void Session::live_step() {
  const int64_t n = generator_->actions_per_step();
  torch::Tensor raw, layout;
  double client_t = 0;
  if (chunker_ && command_.defined()) {
    torch::Tensor velocity, request;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      velocity = velocity_;
      request = std::exchange(command_request_, torch::Tensor());
      client_t = client_t_;  // the newest input this step sees: its frames echo it
    }
    if (request.defined()) command_ = request.clamp(command_min_, command_max_);
    raw = torch::empty({n, command_.size(0)});
    for (int64_t i = 0; i < n; ++i) {
      if (velocity.defined()) command_ = (command_ + velocity * frame_dt_).clamp(command_min_, command_max_);
      raw[i] = command_;
    }
    layout = chunker_->push(raw);  // [n, 384]
  } else {
    layout = torch::zeros({n, data::kUnifiedActionDim});  // no action space: the model runs free
  }
  const auto frames = generator_->step(layout);
  metrics_.observe_step(generator_->last_step_seconds());
  ++step_index_;
  if (recorder_) recorder_->add(raw, layout, frames);
  send_frames(frames, /*droppable=*/true, client_t);
}

}  // namespace dojo::serve
