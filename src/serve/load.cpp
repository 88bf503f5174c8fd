#include "serve/load.h"

#include <boost/asio/ip/tcp.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <boost/beast/websocket.hpp>

#include <sys/socket.h>

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstring>
#include <mutex>
#include <regex>
#include <thread>

#include "core/error.h"
#include "infer/stream_stats.h"

namespace dojo::serve {

namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
namespace net = boost::asio;
using tcp = net::ip::tcp;
using Clock = std::chrono::steady_clock;

namespace {

std::string get(const LoadOptions& o, const std::string& target) {
  net::io_context ioc;
  beast::tcp_stream stream(ioc);
  stream.connect(tcp::endpoint(net::ip::make_address(o.host), o.port));
  http::request<http::string_body> req{http::verb::get, target, 11};
  req.set(http::field::host, o.host);
  if (!o.token.empty()) req.set(http::field::authorization, "Bearer " + o.token);
  http::write(stream, req);
  beast::flat_buffer buffer;
  http::response<http::string_body> res;
  http::read(stream, buffer, res);
  return res.body();
}

double metric(const std::string& text, const std::string& name) {
  const std::regex line("(^|\n)" + name + " ([0-9.e+]+)");
  std::smatch m;
  return std::regex_search(text, m, line) ? std::stod(m[2]) : 0.0;
}

struct SessionResult {
  int64_t frames = 0, errors = 0;
  bool refused = false;                          // declined at the session cap
  int64_t votes = 0, answers = 0, refusals = 0;  // study mode
  double seconds = 0;
  std::vector<double> latencies_ms, server_step_ms;
  std::string failure;
};

// The sockets of running sessions, so a watchdog can unblock a read that would wait forever (a
// server that stalls): blocking Asio reads have no timeout, but a shut-down socket ends them.
struct Sockets {
  std::mutex mutex;
  std::vector<int> fds;
  void add(int fd) {
    std::lock_guard<std::mutex> lock(mutex);
    fds.push_back(fd);
  }
  void remove(int fd) {
    std::lock_guard<std::mutex> lock(mutex);
    fds.erase(std::remove(fds.begin(), fds.end(), fd), fds.end());
  }
  // Registers a socket for its scope.
  struct Registered {
    Sockets& sockets;
    int fd;
    Registered(Sockets& s, int f) : sockets(s), fd(f) { sockets.add(fd); }
    ~Registered() { sockets.remove(fd); }
    Registered(const Registered&) = delete;
    Registered& operator=(const Registered&) = delete;
  };
  void shut_down_all() {
    std::lock_guard<std::mutex> lock(mutex);
    for (int fd : fds) ::shutdown(fd, SHUT_RDWR);
  }
};

// One client session, run to its deadline on the calling thread.
SessionResult run_session(const LoadOptions& o, int index, Sockets& sockets) {
  SessionResult r;
  try {
    net::io_context ioc;
    websocket::stream<beast::tcp_stream> ws(ioc);
    beast::get_lowest_layer(ws).connect(tcp::endpoint(net::ip::make_address(o.host), o.port));
    const Sockets::Registered registered(sockets, beast::get_lowest_layer(ws).socket().native_handle());
    ws.set_option(websocket::stream_base::decorator([&](websocket::request_type& req) {
      if (!o.token.empty()) req.set(http::field::authorization, "Bearer " + o.token);
    }));
    ws.handshake(o.host, "/ws");  // over the session cap: "declined" (the server answered 503)
    const auto send = [&](const nlohmann::json& j) {
      ws.text(true);
      ws.write(net::buffer(j.dump()));
    };
    beast::flat_buffer buffer;
    // The next message: text as JSON, a frame as {"frame": echoed client t}.
    const auto next = [&]() -> nlohmann::json {
      buffer.consume(buffer.size());
      ws.read(buffer);
      const auto data = beast::buffers_to_string(buffer.data());
      if (ws.got_text()) {
        auto j = nlohmann::json::parse(data);
        if (j.value("type", "") == "error") ++r.errors;
        return j;
      }
      double echoed = 0;
      uint32_t step = 0, compute_us = 0;
      if (data.size() >= 32) {
        std::memcpy(&step, data.data() + 8, 4);
        std::memcpy(&compute_us, data.data() + 12, 4);
        std::memcpy(&echoed, data.data() + 16, 8);
      }
      ++r.frames;
      return {{"frame", echoed}, {"step", step}, {"compute_ms", compute_us / 1000.0}};
    };
    nlohmann::json start = {{"type", "start"}, {"mode", o.mode}, {"seed", index}};
    if (!o.model.empty()) start["model"] = o.model;
    send(start);
    nlohmann::json ready;
    while (!(ready = next()).contains("type") || ready["type"] != "ready")
      DOJO_CHECK(ready.value("type", "") != "error",
                 "start refused: " + ready.value("message", std::string()));
    const int64_t per_step = ready["actions_per_step"];
    std::vector<float> command;
    if (ready["command"].is_array()) command = ready["command"].get<std::vector<float>>();
    const auto t0 = Clock::now();
    const auto ms_since = [&](Clock::time_point t) {
      return std::chrono::duration<double, std::milli>(Clock::now() - t).count();
    };
    const auto deadline =
        t0 + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(o.seconds));
    r.frames = 0;
    const auto running = [&] { return Clock::now() < deadline || r.frames < o.min_frames; };
    if (o.mode == "step") {
      for (int64_t s = 0; running(); ++s) {
        nlohmann::json rows = nlohmann::json::array();
        for (int64_t i = 0; i < per_step; ++i) {
          if (command.empty()) {
            rows.push_back(std::vector<float>(384, 0.0f));
          } else {
            auto row = command;
            row[0] += 0.02f * static_cast<float>(s * per_step + i);  // a slow sweep of the first joint
            rows.push_back(row);
          }
        }
        const auto sent = Clock::now();
        send({{"type", "step"}, {"actions", rows}});
        nlohmann::json m;
        while (!(m = next()).contains("type") || (m["type"] != "step_done" && m["type"] != "error")) {
        }
        r.latencies_ms.push_back(ms_since(sent));
        if (m.contains("ms")) r.server_step_ms.push_back(m["ms"].get<double>());
      }
    } else {
      // Live: a control every 100 ms carrying this clock; the server echoes the newest in every
      // frame, so a frame's latency is now minus the echoed value.
      auto last_control = t0 - std::chrono::seconds(1);
      int64_t last_step = -1;
      while (running()) {
        if (Clock::now() - last_control > std::chrono::milliseconds(100) && !command.empty()) {
          std::vector<float> velocity(command.size(), 0.0f);
          velocity[0] = 0.3f;
          send({{"type", "control"}, {"velocity", velocity}, {"t", ms_since(t0)}});
          last_control = Clock::now();
        }
        const auto m = next();
        if (m.contains("frame") && m["frame"].get<double>() > 0)
          r.latencies_ms.push_back(ms_since(t0) - m["frame"].get<double>());
        // One server step time per step (its frames all carry it).
        if (m.contains("step") && m["step"].get<int64_t>() != last_step) {
          last_step = m["step"].get<int64_t>();
          if (m["compute_ms"].get<double>() > 0) r.server_step_ms.push_back(m["compute_ms"].get<double>());
        }
      }
    }
    r.seconds = ms_since(t0) / 1000;
    ws.close(websocket::close_code::normal);
  } catch (const beast::system_error& e) {
    r.refused = e.code() == websocket::error::upgrade_declined;
    r.failure = e.what();
  } catch (const std::exception& e) {
    r.failure = e.what();
  }
  return r;
}

struct HttpAnswer {
  int status = 0;
  nlohmann::json body;
};

// One request on its own connection (registered, so the watchdog can cut a stalled one).
HttpAnswer request(const LoadOptions& o, http::verb verb, const std::string& target, const std::string& body,
                   Sockets& sockets) {
  net::io_context ioc;
  beast::tcp_stream stream(ioc);
  stream.connect(tcp::endpoint(net::ip::make_address(o.host), o.port));
  const Sockets::Registered registered(sockets, stream.socket().native_handle());
  http::request<http::string_body> req{verb, target, 11};
  req.set(http::field::host, o.host);
  if (!o.token.empty()) req.set(http::field::authorization, "Bearer " + o.token);
  if (verb == http::verb::post) {
    req.set(http::field::content_type, "application/json");
    req.body() = body;
    req.prepare_payload();
  }
  http::write(stream, req);
  beast::flat_buffer buffer;
  http::response<http::string_body> res;
  http::read(stream, buffer, res);
  return {static_cast<int>(res.result_int()), nlohmann::json::parse(res.body(), nullptr, false)};
}

// One study voter, run to its deadline: raters, trials and votes over HTTP; a 503 is counted and
// retried after 20 ms. Any other failure (the server gone) ends the voter with what it has.
SessionResult run_voter(const LoadOptions& o, Sockets& sockets) {
  SessionResult r;
  const auto t0 = Clock::now();
  const auto deadline =
      t0 + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(o.seconds));
  const auto call = [&](http::verb verb, const std::string& target, const std::string& body) {
    while (true) {
      auto answer = request(o, verb, target, body, sockets);
      if (answer.status != 503) {
        DOJO_CHECK(answer.status == 200,
                   target + " answered " + std::to_string(answer.status) + ": " + answer.body.dump());
        return answer.body;
      }
      ++r.refusals;
      // Busy answers are retried until shortly past the deadline, then the voter gives up (a
      // server that only ever answers 503 must not keep the run waiting).
      DOJO_CHECK(Clock::now() < deadline + std::chrono::seconds(5),
                 target + " still answered 503 (busy) 5 s past the deadline");
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  };
  try {
    std::string rater;
    while (Clock::now() < deadline) {
      if (rater.empty())
        rater = call(http::verb::post, "/api/study/raters", "").at("rater").get<std::string>();
      const auto trial = call(http::verb::get, "/api/study/next?rater=" + rater, "");
      if (trial.value("done", false)) {
        rater.clear();  // every trial voted on: a new rater sees them all again
        continue;
      }
      nlohmann::json answers = nlohmann::json::object();
      for (const auto& q : trial.at("questions")) answers[q.at("id").get<std::string>()] = "left";
      const nlohmann::json vote = {{"rater", rater}, {"trial", trial.at("trial")}, {"answers", answers}};
      const auto sent = Clock::now();
      call(http::verb::post, "/api/study/vote", vote.dump());
      r.latencies_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - sent).count());
      ++r.votes;
      r.answers += static_cast<int64_t>(answers.size());
    }
  } catch (const std::exception& e) {
    r.failure = e.what();
  }
  r.seconds = std::chrono::duration<double>(Clock::now() - t0).count();
  return r;
}

}  // namespace

LoadReport run_load(const LoadOptions& o) {
  DOJO_CHECK(o.mode == "step" || o.mode == "live" || o.mode == "study",
             "load: mode must be step, live or study");
  DOJO_CHECK(o.sessions >= 1 && o.seconds > 0, "load: needs at least one session and a positive duration");
  boost::system::error_code address_error;
  net::ip::make_address(o.host, address_error);
  DOJO_CHECK(!address_error, "load: --host '" + o.host + "' is not an IP address");
  LoadReport report;
  report.options = o;
  std::string before;
  try {
    before = get(o, "/metrics");
  } catch (const std::exception& e) {
    throw Error("load: cannot reach http://" + o.host + ":" + std::to_string(o.port) +
                "/metrics: " + e.what());
  }
  std::vector<SessionResult> results(o.sessions);
  Sockets sockets;
  std::mutex done_mutex;
  std::condition_variable done_cv;
  int running = o.sessions;
  std::vector<std::thread> threads;
  for (int i = 0; i < o.sessions; ++i)
    threads.emplace_back([&, i] {
      results[i] = o.mode == "study" ? run_voter(o, sockets) : run_session(o, i, sockets);
      std::lock_guard<std::mutex> lock(done_mutex);
      --running;
      done_cv.notify_all();
    });
  {  // A minute past the deadline, whatever still waits on the server is cut off (and reported).
    std::unique_lock<std::mutex> lock(done_mutex);
    const auto give_up = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                            std::chrono::duration<double>(o.seconds + 60));
    if (!done_cv.wait_until(lock, give_up, [&] { return running == 0; })) sockets.shut_down_all();
  }
  for (auto& t : threads) t.join();
  std::string after;
  try {
    after = get(o, "/metrics");
  } catch (const std::exception& e) {
    // Reported, not thrown: a run that killed its server still counts what was acknowledged.
    report.server_alive_after = false;
    report.failures.push_back("the server stopped answering /metrics after the run: " +
                              std::string(e.what()));
  }
  std::vector<double> latencies, steps;
  for (const auto& r : results) {
    report.votes_acknowledged += r.votes;
    report.answers_acknowledged += r.answers;
    report.refusals += r.refusals;
    if (r.refused) {
      ++report.refused_sessions;
      continue;
    }
    if (!r.failure.empty()) {
      ++report.failed_sessions;
      report.failures.push_back(r.failure);
      if (o.mode != "study") continue;
    }
    if (o.mode != "study") {  // voters see no frames
      report.frames.push_back(r.frames);
      report.frames_per_second.push_back(r.seconds > 0 ? r.frames / r.seconds : 0);
    }
    report.errors += r.errors;
    latencies.insert(latencies.end(), r.latencies_ms.begin(), r.latencies_ms.end());
    steps.insert(steps.end(), r.server_step_ms.begin(), r.server_step_ms.end());
  }
  report.server_step_ms_p50 = infer::percentile(steps, 0.5);
  report.server_step_ms_p95 = infer::percentile(steps, 0.95);
  report.latency_ms_p50 = infer::percentile(latencies, 0.5);
  report.latency_ms_p95 = infer::percentile(latencies, 0.95);
  report.latency_ms_p99 = infer::percentile(latencies, 0.99);
  report.server_rss_mib_before = metric(before, "process_resident_memory_bytes") / (1 << 20);
  report.server_rss_mib_after = metric(after, "process_resident_memory_bytes") / (1 << 20);
  report.frames_dropped = static_cast<int64_t>(metric(after, "dojo_frames_dropped_total") -
                                               metric(before, "dojo_frames_dropped_total"));
  return report;
}

nlohmann::json LoadReport::to_json() const {
  return {{"mode", options.mode},
          {"sessions", options.sessions},
          {"seconds", options.seconds},
          {"frames", frames},
          {"frames_per_second", frames_per_second},
          {"latency_ms_p50", latency_ms_p50},
          {"latency_ms_p95", latency_ms_p95},
          {"latency_ms_p99", latency_ms_p99},
          {"server_step_ms_p50", server_step_ms_p50},
          {"server_step_ms_p95", server_step_ms_p95},
          {"errors", errors},
          {"failed_sessions", failed_sessions},
          {"refused_sessions", refused_sessions},
          {"refusals", refusals},
          {"votes_acknowledged", votes_acknowledged},
          {"votes_per_second", votes_acknowledged / options.seconds},
          {"answers_acknowledged", answers_acknowledged},
          {"server_alive_after", server_alive_after},
          {"failures", failures},
          {"frames_dropped", frames_dropped},
          {"server_rss_mib_before", server_rss_mib_before},
          {"server_rss_mib_after", server_rss_mib_after}};
}

}  // namespace dojo::serve
