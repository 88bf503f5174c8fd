#include "serve/external_policy.h"

#include "data/action_rows.h"

#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <boost/asio/ip/tcp.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/websocket.hpp>

#include <chrono>
#include <cstring>
#include <optional>
#include <thread>
#include <vector>

#include "core/error.h"
#include "core/log.h"
#include "io/jpeg.h"
#include "serve/session.h"

extern char** environ;

namespace dojo::serve {
namespace {

namespace beast = boost::beast;
namespace websocket = beast::websocket;
namespace net = boost::asio;
using tcp = net::ip::tcp;
using Clock = std::chrono::steady_clock;

std::vector<float> to_floats(const torch::Tensor& t) {
  const auto c = t.to(torch::kFloat32).contiguous();
  return {c.data_ptr<float>(), c.data_ptr<float>() + c.numel()};
}

class ExternalPolicy : public eval::Policy {
 public:
  explicit ExternalPolicy(ExternalPolicyOptions options) : options_(std::move(options)) {
    DOJO_CHECK(!options_.name.empty() && !options_.command.empty(),
               "external policy: a name and a command are needed");
  }

  ~ExternalPolicy() override { finish(); }

  const std::string& name() const override { return options_.name; }

  void reset(const eval::EpisodeStart& start) override {
    if (!ws_) connect();  // the process starts when its first episode does, not while others run
    finish_episode();
    start_ = start;
    started_ = false;
    step_ = 0;
  }

  torch::Tensor act(const torch::Tensor& frames, const torch::Tensor& last_command, int64_t n) override {
    const int64_t width = last_command.numel();
    if (!started_) {
      for (;;) {
        const auto m = receive();
        if (m.value("type", "") == "start") break;
        reply_error(m.value("type", "") == "step" ? "a new episode begins: send {\"type\":\"start\"} first"
                                                  : "expected {\"type\":\"start\"}");
      }
      send_text({{"type", "ready"},
                 {"mode", "step"},
                 {"episode", "scene-" + std::to_string(start_.index)},
                 {"seed", start_.seed},
                 {"width", frames.size(2)},
                 {"height", frames.size(1)},
                 {"actions_per_step", n},
                 {"fps", 10.0},
                 {"command", to_floats(last_command)}});
      send_frames(frames.narrow(0, frames.size(0) - 1, 1));
      started_ = true;
    } else {
      send_frames(frames);
      send_text({{"type", "step_done"}, {"step", step_}, {"frames", frames.size(0)}, {"done", false}});
    }
    for (;;) {
      const auto m = receive();
      if (m.value("type", "") != "step") {
        reply_error("expected {\"type\":\"step\", \"actions\": [...]}");
        continue;
      }
      try {
        DOJO_CHECK(m.contains("actions"), "step: missing 'actions'");
        const auto rows = data::action_rows_from_json(m["actions"], "step.actions", 64);  // [n, w]
        DOJO_CHECK(rows.size(0) == n && rows.size(1) == width,
                   "step.actions: expected " + std::to_string(n) + " raw commands of " +
                       std::to_string(width) + " values, got [" + std::to_string(rows.size(0)) + ", " +
                       std::to_string(rows.size(1)) + "]");
        awaiting_ = true;
        ++step_;
        return rows;
      } catch (const Error& e) {
        reply_error(e.what());
      }
    }
  }

  // Ends the last episode, closes the connection and stops the process. Never throws.
  void finish() override {
    if (ws_) {
      try {
        finish_episode();
        wait([&](auto handler) { ws_->async_close(websocket::close_code::normal, handler); }, "closing", 5);
      } catch (const std::exception& e) {
        LOG_DEBUG("external policy '", options_.name, "': ", e.what());
      }
      beast::error_code ignored;
      beast::get_lowest_layer(*ws_).close(ignored);
      ws_.reset();
    }
    stop_process();
  }

 private:
  [[noreturn]] void fail(const std::string& what) const {
    throw Error("external policy '" + options_.name + "': " + what);
  }

  void connect() {
    acceptor_.open(tcp::v4());
    acceptor_.bind({net::ip::make_address("127.0.0.1"), 0});
    acceptor_.listen(1);
    const auto url = "ws://127.0.0.1:" + std::to_string(acceptor_.local_endpoint().port()) + "/ws";
    spawn(url);
    LOG_INFO("external policy '", options_.name, "': started `", options_.command, "`, waiting at ", url);
    ws_.emplace(ioc_);
    try {
      wait([&](auto handler) { acceptor_.async_accept(ws_->next_layer(), handler); }, "before connecting");
      acceptor_.close();  // one connection per policy
      wait([&](auto handler) { ws_->async_accept(handler); }, "during the WebSocket handshake");
    } catch (...) {
      ws_.reset();
      stop_process();
      throw;
    }
    ws_->read_message_max(1 << 20);
  }

  void spawn(const std::string& url) {
    std::vector<std::string> env;
    for (char** e = environ; *e; ++e)
      if (std::string(*e).rfind("DOJO_POLICY_URL=", 0) != 0) env.emplace_back(*e);
    env.push_back("DOJO_POLICY_URL=" + url);
    std::vector<char*> envp;
    for (auto& e : env) envp.push_back(e.data());
    envp.push_back(nullptr);
    std::string sh = "/bin/sh", flag = "-c", command = options_.command;
    std::vector<char*> argv = {sh.data(), flag.data(), command.data(), nullptr};
    posix_spawn_file_actions_t actions;
    posix_spawn_file_actions_init(&actions);
    // The policy's stdout goes to our stderr: our stdout carries the evaluation's table. It
    // inherits no other descriptor of ours (the listening socket, other policies' connections).
    posix_spawn_file_actions_adddup2(&actions, STDERR_FILENO, STDOUT_FILENO);
    posix_spawn_file_actions_addclosefrom_np(&actions, 3);
    // Its own process group, so that stopping it reaches what the shell started too.
    posix_spawnattr_t attributes;
    posix_spawnattr_init(&attributes);
    posix_spawnattr_setflags(&attributes, POSIX_SPAWN_SETPGROUP);
    posix_spawnattr_setpgroup(&attributes, 0);
    const int rc = posix_spawn(&pid_, sh.c_str(), &actions, &attributes, argv.data(), envp.data());
    posix_spawnattr_destroy(&attributes);
    posix_spawn_file_actions_destroy(&actions);
    if (rc != 0) {
      pid_ = -1;
      fail("cannot start `" + options_.command + "`: " + std::strerror(rc));
    }
    exit_.reset();
  }

  // The process's exit, once it has exited ("status 1", "signal 9").
  std::optional<std::string> exited() {
    if (pid_ <= 0) return exit_;
    int status = 0;
    if (waitpid(pid_, &status, WNOHANG) != pid_) return std::nullopt;
    pid_ = -1;
    exit_ = WIFEXITED(status) ? "status " + std::to_string(WEXITSTATUS(status))
                              : "signal " + std::to_string(WTERMSIG(status));
    return exit_;
  }

  void stop_process() {
    if (pid_ <= 0) return;
    const pid_t group = pid_;
    // A policy that saw the connection close should leave by itself; then it is asked, then told.
    for (const int signal : {0, SIGTERM}) {
      if (signal) kill(-group, signal);
      for (int i = 0; i < 50 && !exited(); ++i) std::this_thread::sleep_for(std::chrono::milliseconds(100));
      if (pid_ <= 0) break;
    }
    kill(-group, SIGKILL);  // whatever of its group is left
    if (pid_ > 0) {
      waitpid(pid_, nullptr, 0);
      pid_ = -1;
    }
  }

  // Runs one asynchronous operation to completion, or fails after `timeout_s` (default: the
  // options') or when the process exits first. `begin(handler)` starts the operation.
  template <class Begin>
  void wait(Begin begin, const std::string& what, double timeout_s = 0) {
    bool done = false;
    beast::error_code ec;
    ioc_.restart();
    begin([&](beast::error_code e, auto&&...) {
      done = true;
      ec = e;
    });
    const double limit = timeout_s > 0 ? timeout_s : options_.timeout_s;
    const auto deadline = Clock::now() + std::chrono::duration<double>(limit);
    std::string problem;
    while (!done) {
      ioc_.run_for(std::chrono::milliseconds(100));
      if (done) break;
      if (const auto status = exited()) {
        problem = "the process exited (" + *status + ") " + what;
      } else if (Clock::now() > deadline) {
        problem = "no answer in " + std::to_string(static_cast<int>(limit)) + " s " + what;
      }
      if (!problem.empty()) {
        // Cancel, and let the handler run while `done` and `ec` still exist.
        beast::error_code ignored;
        acceptor_.close(ignored);
        if (ws_) beast::get_lowest_layer(*ws_).close(ignored);
        ioc_.restart();
        ioc_.run();
        fail(problem);
      }
    }
    if (ec) fail(what + ": " + ec.message());
  }

  // The next text message as a JSON object; anything else is answered with an error.
  nlohmann::json receive() {
    for (;;) {
      beast::flat_buffer buffer;
      wait([&](auto handler) { ws_->async_read(buffer, handler); }, "waiting for a message");
      if (!ws_->got_text()) {
        reply_error("binary messages are not part of policy evaluation");
        continue;
      }
      auto m = nlohmann::json::parse(beast::buffers_to_string(buffer.data()), nullptr, false);
      if (m.is_object() && m.contains("type") && m["type"].is_string()) return m;
      reply_error("expected a JSON object with a string 'type'");
    }
  }

  // With the same deadline as a read: a policy that stops reading cannot hold the evaluation.
  void write(bool binary, const std::string& data) {
    ws_->binary(binary);
    wait([&](auto handler) { ws_->async_write(net::buffer(data), handler); }, "while sending");
  }
  void send_text(const nlohmann::json& message) { write(false, message.dump()); }
  void reply_error(const std::string& message) { send_text({{"type", "error"}, {"message", message}}); }

  void send_frames(const torch::Tensor& frames) {  // [k, H, W, 3] uint8
    const double ms = std::chrono::duration<double, std::milli>(Clock::now() - t0_).count();
    for (int64_t i = 0; i < frames.size(0); ++i)
      write(true, frame_message(io::encode_jpeg(frames[i], options_.jpeg_quality), sequence_++,
                                static_cast<uint32_t>(step_), 0, 0, ms));
  }

  // The episode's last step is answered when the next episode begins (or the policy finishes).
  void finish_episode() {
    if (!awaiting_) return;
    awaiting_ = false;
    send_text({{"type", "step_done"}, {"step", step_}, {"frames", 0}, {"done", true}});
  }

  ExternalPolicyOptions options_;
  net::io_context ioc_;
  tcp::acceptor acceptor_{ioc_};
  std::optional<websocket::stream<tcp::socket>> ws_;  // while connected
  pid_t pid_ = -1;
  std::optional<std::string> exit_;
  eval::EpisodeStart start_;
  bool started_ = false, awaiting_ = false;
  int64_t step_ = 0;
  uint32_t sequence_ = 0;
  Clock::time_point t0_ = Clock::now();
};

}  // namespace

std::unique_ptr<eval::Policy> make_external_policy(const ExternalPolicyOptions& options) {
  return std::make_unique<ExternalPolicy>(options);
}

}  // namespace dojo::serve
