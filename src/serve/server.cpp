#include "serve/server.h"

#include <boost/asio/dispatch.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/ssl.hpp>
#include <boost/asio/strand.hpp>
#include <boost/asio/thread_pool.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <boost/beast/ssl.hpp>
#include <boost/beast/websocket.hpp>
#include <boost/beast/websocket/ssl.hpp>

#include <algorithm>
#include <cctype>
#include <condition_variable>
#include <deque>
#include <mutex>
#include <optional>
#include <string_view>
#include <thread>
#include <vector>

#include "core/error.h"
#include "core/log.h"
#include "data/embodiments.h"
#include "serve/model_host.h"
#include "serve/pages.h"
#include "serve/rollout_api.h"
#include "serve/session.h"
#include "serve/study_api.h"

namespace dojo::serve {

namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
namespace net = boost::asio;
using tcp = net::ip::tcp;

struct Server::Impl {
  ServeOptions options;
  std::shared_ptr<ModelHost> host;
  std::unique_ptr<StudyApi> study;  // with --study
  ServerMetrics metrics;
  net::io_context ioc;
  // Keeps the IO threads running while no socket operation is pending (a study request or a
  // rollout computing aside will still post its answer to them); released by stop().
  std::optional<net::executor_work_guard<net::io_context::executor_type>> keep_running;
  tcp::acceptor acceptor{net::make_strand(ioc)};  // its handlers and its close at stop() in turn
  std::optional<net::ssl::context> tls;           // with --tls-cert / --tls-key: every connection is HTTPS
  std::vector<std::thread> threads;
  std::atomic<int> sessions{0};  // WebSocket sessions and rollout jobs in flight
  // The study's requests: a fixed pool (a vote waits for its fsync, so not on the IO threads) and
  // a cap on those queued or running, so a crowd of voters costs threads and memory in bounds.
  std::optional<net::thread_pool> study_pool;
  std::atomic<int> study_requests{0};
  std::atomic<bool> stopping{false};
  std::mutex stop_mutex;  // a second stop() (the destructor's) waits for the first to end
  bool stopped = false;
  // Work that outlives its connection: rollout jobs and sessions winding down (recordings being
  // written). Detached threads, counted: stop() waits for all of them.
  std::mutex background_mutex;
  std::condition_variable background_done;
  int background_running = 0;
  std::mutex connections_mutex;
  // A connection's close, posted to its strand; the posted handler holds `running` until it has
  // run, so stop() can wait for every close before it stops the IO threads.
  using CloseFn = std::function<void(std::shared_ptr<void> running)>;
  enum class ConnectionKind { kWebSocket, kHttp };
  struct Closer {
    std::weak_ptr<void> connection;
    ConnectionKind kind;
    CloseFn close;
  };
  std::vector<Closer> closers;  // close every live connection at stop()
  // Registers `close` to run at stop() while `connection` lives; forgets closers of connections
  // gone since, so the list tracks live ones.
  void add_closer(std::weak_ptr<void> connection, ConnectionKind kind, CloseFn close) {
    std::lock_guard<std::mutex> lock(connections_mutex);
    closers.erase(std::remove_if(closers.begin(), closers.end(),
                                 [](const Closer& c) { return c.connection.expired(); }),
                  closers.end());
    closers.push_back({std::move(connection), kind, std::move(close)});
  }
  // Runs `post` (which posts work holding `running` to the IO threads) and waits until that work
  // has run (at most 5 s): a close still queued when the IO threads stop would never run.
  void post_and_wait(const CloseFn& post) {
    auto running = std::make_shared<int>(0);
    post(running);
    for (int waited = 0; !threads.empty() && running.use_count() > 1 && waited < 500; ++waited)
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  void close_connections(ConnectionKind kind) {
    post_and_wait([&](std::shared_ptr<void> running) {
      std::lock_guard<std::mutex> lock(connections_mutex);
      for (auto& closer : closers)
        if (closer.kind == kind) closer.close(running);
    });
  }

  // `work` wrapped so that stop() waits for it: counted from now until it has run (and released
  // what it holds), its exception logged under `what`.
  std::function<void()> counted(std::function<void()> work, const char* what) {
    {
      std::lock_guard<std::mutex> lock(background_mutex);
      ++background_running;
    }
    return [this, what, work = std::move(work)]() mutable {
      try {
        work();
      } catch (const std::exception& e) {
        LOG_WARN("serve: ", what, " failed: ", e.what());
      }
      work = nullptr;  // release what it holds before counting it done
      std::lock_guard<std::mutex> lock(background_mutex);
      --background_running;
      background_done.notify_all();
    };
  }
  void wait_for_background() {
    std::unique_lock<std::mutex> lock(background_mutex);
    background_done.wait(lock, [this] { return background_running == 0; });
  }
  void run_in_background(std::function<void()> work) {
    std::thread(counted(std::move(work), "background work")).detach();
  }
  // The study's requests (a vote waits for its fsync) on the bounded pool.
  void run_on_study_pool(std::function<void()> work) {
    net::post(*study_pool, counted(std::move(work), "study request"));
  }
  bool authorised(const http::request<http::string_body>& req) const;
  void accept();
};

namespace {

using Request = http::request<http::string_body>;
using Response = http::response<http::string_body>;

Response reply(const Request& req, http::status status, const std::string& type, std::string body) {
  Response res{status, req.version()};
  res.set(http::field::server, "dojo");
  res.set(http::field::content_type, type);
  res.set(http::field::cache_control, "no-store");
  res.keep_alive(req.keep_alive());
  res.body() = std::move(body);
  res.prepare_payload();
  return res;
}

Response json_error(const Request& req, http::status status, const std::string& message) {
  return reply(req, status, "application/json", nlohmann::json{{"error", message}}.dump());
}

bool is_embedded_page(const std::string& path) {
  for (const auto& page : embedded_pages())
    if (path == page.path) return true;
  return false;
}

// "/NAME.mapping.json" of a robot of the user's embodiment table: its teleoperation controls.
const data::EmbodimentSpec* user_robot_mapping(const std::string& path) {
  const std::string suffix = ".mapping.json";
  if (path.size() <= suffix.size() + 1 ||
      path.compare(path.size() - suffix.size(), suffix.size(), suffix) != 0)
    return nullptr;
  return data::find_user_embodiment(path.substr(1, path.size() - suffix.size() - 1));
}

std::string path_of(beast::string_view target) {
  const auto q = target.find('?');
  return std::string(target.substr(0, q));
}

std::string query_param(beast::string_view target, const std::string& key) {
  const auto q = target.find('?');
  if (q == beast::string_view::npos) return "";
  std::string query(target.substr(q + 1));
  size_t start = 0;
  while (start <= query.size()) {
    const auto end = std::min(query.find('&', start), query.size());
    const auto item = query.substr(start, end - start);
    const auto eq = item.find('=');
    if (eq != std::string::npos && item.substr(0, eq) == key) return item.substr(eq + 1);
    start = end + 1;
  }
  return "";
}

// A WebSocket connection: carries a Session's messages. Writes go out one at a time on the
// connection's strand; live frames wait in a short queue whose oldest frame is dropped when a
// slow client lets it grow past two steps (latest frames win, memory stays bounded).
template <class Stream>  // beast::tcp_stream, or beast::ssl_stream<beast::tcp_stream> for HTTPS
class WsConnection : public std::enable_shared_from_this<WsConnection<Stream>> {
  using std::enable_shared_from_this<WsConnection<Stream>>::shared_from_this;

 public:
  WsConnection(Stream&& stream, Server::Impl& server) : ws_(std::move(stream)), server_(server) {}

  void accept(Request req) {
    ws_.set_option(websocket::stream_base::timeout::suggested(beast::role_type::server));
    ws_.read_message_max(server_.options.max_message_bytes);
    ws_.async_accept(req, beast::bind_front_handler(&WsConnection<Stream>::on_accept, shared_from_this()));
  }

 private:
  void on_accept(beast::error_code ec) {
    if (ec) return release();
    server_.metrics.session_opened();
    opened_ = true;
    SessionOptions o;
    o.jpeg_quality = server_.options.jpeg_quality;
    o.fps = server_.options.fps;
    o.recordings = server_.options.recordings;
    std::weak_ptr<WsConnection<Stream>> weak = shared_from_this();
    session_ = std::make_unique<Session>(*server_.host, o, server_.metrics, [weak](Outgoing out) {
      if (auto self = weak.lock())
        net::post(self->ws_.get_executor(),
                  [self, out = std::move(out)]() mutable { self->enqueue(std::move(out)); });
    });
    server_.add_closer(weak, Server::Impl::ConnectionKind::kWebSocket, [weak](std::shared_ptr<void> running) {
      if (auto self = weak.lock()) net::post(self->ws_.get_executor(), [self, running] { self->shutdown(); });
    });
    // Upgraded after stop() closed the WebSockets it knew of: nobody would close this one.
    if (server_.stopping) return shutdown();
    read();
  }

  void read() {
    ws_.async_read(buffer_, beast::bind_front_handler(&WsConnection<Stream>::on_read, shared_from_this()));
  }

  void on_read(beast::error_code ec, size_t) {
    if (ec) return release();  // closed, timed out, or a message over the size limit
    const auto data = buffer_.cdata();
    const std::string_view message(static_cast<const char*>(data.data()), data.size());
    if (ws_.got_text())
      session_->on_text(message);
    else
      session_->on_binary(message);
    buffer_.consume(buffer_.size());
    read();
  }

  void enqueue(Outgoing out) {
    if (released_) return;
    if (out.droppable) {
      pending_frames_.push_back(std::move(out));
      if (pending_frames_.size() > kMaxPendingFrames) {  // the client is slower than the model
        pending_frames_.pop_front();
        server_.metrics.frames_dropped(1);
      }
    } else {
      queued_bytes_ += out.data.size();
      queue_.push_back(std::move(out));
      if (queued_bytes_ > kMaxQueuedBytes) {
        LOG_WARN("serve: a client is not reading its frames; closing its session");
        server_.metrics.error();
        return shutdown();
      }
    }
    write_next();
  }

  void write_next() {
    if (writing_ || released_) return;
    if (!queue_.empty()) {
      current_ = std::move(queue_.front());
      queue_.pop_front();
      queued_bytes_ -= current_.data.size();
    } else if (!pending_frames_.empty()) {
      current_ = std::move(pending_frames_.front());
      pending_frames_.pop_front();
    } else {
      return;
    }
    writing_ = true;
    ws_.binary(current_.binary);
    ws_.async_write(net::buffer(current_.data),
                    beast::bind_front_handler(&WsConnection<Stream>::on_write, shared_from_this()));
  }

  void on_write(beast::error_code ec, size_t) {
    writing_ = false;
    if (ec) return release();
    write_next();
  }

  void shutdown() {
    if (released_) return;
    ws_.async_close(websocket::close_code::going_away,
                    [self = shared_from_this()](beast::error_code) { self->release(); });
  }

  // The session ends on another thread: its worker may be inside a model step, and a recording
  // in progress is written before the thread ends.
  void release() {
    if (released_) return;
    released_ = true;
    queue_.clear();
    pending_frames_.clear();
    if (session_) {
      session_->close();
      server_.run_in_background(
          [session = std::shared_ptr<Session>(std::move(session_))]() mutable { session.reset(); });
    }
    --server_.sessions;  // first: a client that sees the session gone may open the next at once
    if (opened_) server_.metrics.session_closed();
  }

  websocket::stream<Stream> ws_;
  Server::Impl& server_;
  beast::flat_buffer buffer_;
  std::unique_ptr<Session> session_;
  std::deque<Outgoing> queue_;
  // Live frames waiting to be written: two steps' worth; beyond that the oldest is dropped.
  // (24: two teacher chunks, six student steps.)
  static constexpr size_t kMaxPendingFrames = 24;
  // Step-mode replies are never dropped; a client that sends steps but does not read its frames is
  // disconnected when this much waits for it.
  static constexpr size_t kMaxQueuedBytes = 64 << 20;
  size_t queued_bytes_ = 0;
  std::deque<Outgoing> pending_frames_;
  Outgoing current_;
  bool writing_ = false, released_ = false, opened_ = false;
};

template <class Stream>
class HttpConnection : public std::enable_shared_from_this<HttpConnection<Stream>> {
  using std::enable_shared_from_this<HttpConnection<Stream>>::shared_from_this;
  static constexpr bool kTls = !std::is_same_v<Stream, beast::tcp_stream>;

 public:
  HttpConnection(tcp::socket&& socket, Server::Impl& server)
      : stream_(make(std::move(socket), server)), executor_(stream_.get_executor()), server_(server) {}
  void run() {
    // At stop() a connection still open (between requests, or one whose answer could not be
    // written) is closed, so that its client sees the server go instead of waiting on a socket
    // nobody serves.
    std::weak_ptr<HttpConnection> weak = shared_from_this();
    server_.add_closer(weak, Server::Impl::ConnectionKind::kHttp, [weak](std::shared_ptr<void> running) {
      if (auto self = weak.lock())
        net::post(self->executor_, [self, running] {
          if (self->upgraded_) return;  // the stream now belongs to a WebSocket, closed by its own closer
          // An answer being written (a rollout's video) goes out whole first; stop() waits for it
          // while `running` is held here (at most its 5 s).
          if (self->writing_) {
            self->close_after_write_ = std::move(running);
            return;
          }
          beast::get_lowest_layer(self->stream_).close();
        });
    });
    net::dispatch(executor_, [self = shared_from_this()] {
      if constexpr (kTls) {
        beast::get_lowest_layer(self->stream_).expires_after(std::chrono::seconds(30));
        self->stream_.async_handshake(net::ssl::stream_base::server, [self](beast::error_code ec) {
          if (ec) return self->close();  // not TLS, or a certificate the client refused
          self->read();
        });
      } else {
        self->read();
      }
    });
  }

 private:
  static Stream make(tcp::socket&& socket, Server::Impl& server) {
    if constexpr (kTls)
      return Stream(std::move(socket), *server.tls);
    else
      return Stream(std::move(socket));
  }

  void read() {
    parser_.emplace();
    parser_->body_limit(server_.options.max_message_bytes);
    parser_->header_limit(16 * 1024);
    beast::get_lowest_layer(stream_).expires_after(std::chrono::seconds(30));
    http::async_read(stream_, buffer_, *parser_,
                     beast::bind_front_handler(&HttpConnection<Stream>::on_read, shared_from_this()));
  }

  void on_read(beast::error_code ec, size_t) {
    // A TLS client that leaves without close_notify is a client leaving, not a malformed request.
    if (ec == http::error::end_of_stream || ec == net::ssl::error::stream_truncated) return close();
    if (ec == http::error::body_limit) {
      server_.metrics.error();
      Request req;
      return write(json_error(req, http::status::payload_too_large, "request body over the limit"), true);
    }
    if (ec) {  // malformed request or timeout: answer what can be answered, then close
      if (ec != beast::error::timeout && ec != net::error::operation_aborted) {
        server_.metrics.error();
        Request req;
        return write(json_error(req, http::status::bad_request, "malformed HTTP request"), true);
      }
      return close();
    }
    server_.metrics.request();
    auto req = parser_->release();
    // A stopping server takes no new work: stop() waits for what is running, and clients that keep
    // sending would keep it waiting.
    if (server_.stopping)
      return write(json_error(req, http::status::service_unavailable, "the server is stopping"), true);
    const auto path = path_of(req.target());
    // The embedded pages and scripts hold no secrets and a browser fetches scripts without the
    // token; everything they call (the API, the WebSocket, the clips) needs it.
    const bool public_page = path == "/health" || path == "/study" || is_embedded_page(path) ||
                             user_robot_mapping(path) != nullptr;
    if (!public_page && !server_.authorised(req)) {
      server_.metrics.error();
      return write(json_error(req, http::status::unauthorized,
                              "missing or wrong token: send it as an Authorization: Bearer header or the "
                              "dojo_token cookie (open the page as /#token=...), never in the URL"));
    }
    if (websocket::is_upgrade(req)) {
      if (path != "/ws") return write(json_error(req, http::status::not_found, "WebSocket endpoint is /ws"));
      if (!server_.host->ready())
        return write(json_error(req, http::status::service_unavailable, "models loading"));
      if (server_.sessions.fetch_add(1) >= server_.options.max_sessions) {
        --server_.sessions;
        server_.metrics.session_refused();
        return write(
            json_error(req, http::status::service_unavailable,
                       "all " + std::to_string(server_.options.max_sessions) + " sessions are in use"));
      }
      beast::get_lowest_layer(stream_).expires_never();
      upgraded_ = true;
      std::make_shared<WsConnection<Stream>>(std::move(stream_), server_)->accept(std::move(req));
      return;
    }
    route(std::move(req), path);
  }

  void route(Request req, const std::string& path) {
    const bool get = req.method() == http::verb::get || req.method() == http::verb::head;
    if (path == "/health" && get) {
      const bool ready = server_.host->ready();
      return write(reply(req, ready ? http::status::ok : http::status::service_unavailable,
                         "application/json", nlohmann::json{{"status", ready ? "ok" : "loading"}}.dump()));
    }
    if (path == "/metrics" && get)
      return write(
          reply(req, http::status::ok, "text/plain; version=0.0.4", server_.metrics.prometheus_text()));
    if (path == "/api/capabilities" && get)
      return write(reply(req, http::status::ok, "application/json", server_.host->capabilities().dump()));
    const auto page_path = path == "/study" ? std::string("/study.html") : path;
    for (const auto& page : embedded_pages())
      if (page_path == page.path && get)
        return write(reply(req, http::status::ok, page.content_type, page.content));
    if (const auto* robot = user_robot_mapping(path); robot != nullptr && get)
      return write(reply(req, http::status::ok, "application/json", data::teleop_mapping(*robot).dump()));
    if (path == "/v1/rollout") {
      if (req.method() != http::verb::post)
        return write(json_error(req, http::status::method_not_allowed, "use POST"));
      if (!server_.host->ready())
        return write(json_error(req, http::status::service_unavailable, "models loading"));
      if (server_.sessions.fetch_add(1) >= server_.options.max_sessions) {
        --server_.sessions;
        server_.metrics.session_refused();
        return write(json_error(req, http::status::service_unavailable, "the server is busy; retry later"));
      }
      // Minutes of work must not hold an IO thread: run it aside, answer on this connection.
      auto self = shared_from_this();
      server_.run_in_background([self, req = std::move(req)]() mutable {
        const auto& o = self->server_.options;
        auto r = run_rollout_request(*self->server_.host, req.body(), self->server_.metrics,
                                     RolloutLimits{o.max_rollout_frames, o.max_rollout_seconds,
                                                   o.jpeg_quality, &self->server_.stopping});
        --self->server_.sessions;
        auto res = reply(req, static_cast<http::status>(r.status), r.content_type, std::move(r.body));
        net::post(self->executor_, [self, res = std::move(res)]() mutable { self->write(std::move(res)); });
      });
      return;
    }
    if (StudyApi::handles(path)) {
      if (!server_.study)
        return write(json_error(req, http::status::not_found, "this server runs no study (--study DIR)"));
      // A vote waits for its fsync (synchronous=FULL); keep that off the IO threads, on a pool.
      if (server_.study_requests.fetch_add(1) >= server_.options.max_study_requests) {
        --server_.study_requests;
        server_.metrics.error();
        return write(json_error(req, http::status::service_unavailable, "the study is busy; retry later"));
      }
      auto self = shared_from_this();
      server_.run_on_study_pool([self, req = std::move(req), path]() mutable {
        --self->server_.study_requests;
        auto r = self->server_.study->handle(std::string(req.method_string()), path,
                                             query_param(req.target(), "rater"), req.body(),
                                             std::string(req[http::field::user_agent]));
        if (r.status >= 400) self->server_.metrics.error();
        auto res = reply(req, static_cast<http::status>(r.status), r.content_type, std::move(r.body));
        net::post(self->executor_, [self, res = std::move(res)]() mutable { self->write(std::move(res)); });
      });
      return;
    }
    server_.metrics.error();
    write(json_error(req, http::status::not_found, "no route " + path));
  }

  void write(Response res, bool close_after = false) {
    if (close_after) res.keep_alive(false);
    response_ = std::make_shared<Response>(std::move(res));
    beast::get_lowest_layer(stream_).expires_after(std::chrono::seconds(60));
    writing_ = true;
    http::async_write(stream_, *response_, [self = shared_from_this()](beast::error_code ec, size_t) {
      self->writing_ = false;
      if (self->close_after_write_) {  // stop() closed the connection while this answer went out
        beast::get_lowest_layer(self->stream_).close();
        self->close_after_write_.reset();
        return;
      }
      if (ec || !self->response_->keep_alive()) return self->close();
      self->read();
    });
  }

  void close() {
    beast::error_code ec;
    beast::get_lowest_layer(stream_).socket().shutdown(tcp::socket::shutdown_send, ec);
  }

  Stream stream_;
  // The connection's strand, kept apart from the stream, which a WebSocket upgrade moves away.
  net::any_io_executor executor_;
  Server::Impl& server_;
  bool upgraded_ = false, writing_ = false;
  std::shared_ptr<void> close_after_write_;  // stop()'s hold while an answer is being written
  beast::flat_buffer buffer_;
  std::optional<http::request_parser<http::string_body>> parser_;
  std::shared_ptr<Response> response_;
};

}  // namespace

namespace {

// Equal strings, in a time that depends on their lengths only (not on where they first differ).
bool same_secret(std::string_view given, std::string_view expected) {
  unsigned char differ = given.size() == expected.size() ? 0 : 1;
  for (size_t i = 0; i < given.size(); ++i)
    differ |= static_cast<unsigned char>(given[i] ^ expected[i % std::max<size_t>(1, expected.size())]);
  return differ == 0;
}

// The value of cookie `name` in a Cookie header ("a=1; dojo_token=xyz"), or "" when absent.
std::string cookie_value(std::string_view header, std::string_view name) {
  while (!header.empty()) {
    const auto end = header.find(';');
    auto pair = header.substr(0, end);
    while (!pair.empty() && pair.front() == ' ') pair.remove_prefix(1);
    if (pair.size() > name.size() && pair.substr(0, name.size()) == name && pair[name.size()] == '=')
      return std::string(pair.substr(name.size() + 1));
    if (end == std::string_view::npos) break;
    header.remove_prefix(end + 1);
  }
  return "";
}

std::string percent_decoded(std::string_view text) {
  std::string out;
  for (size_t i = 0; i < text.size(); ++i) {
    if (text[i] == '%' && i + 2 < text.size() && std::isxdigit(static_cast<unsigned char>(text[i + 1])) &&
        std::isxdigit(static_cast<unsigned char>(text[i + 2]))) {
      out += static_cast<char>(std::stoi(std::string(text.substr(i + 1, 2)), nullptr, 16));
      i += 2;
    } else {
      out += text[i];
    }
  }
  return out;
}

}  // namespace

bool Server::Impl::authorised(const http::request<http::string_body>& req) const {
  if (options.token.empty()) return true;
  const std::string_view header(req[http::field::authorization].data(),
                                req[http::field::authorization].size());
  if (header.size() > 7 && header.substr(0, 7) == "Bearer " && same_secret(header.substr(7), options.token))
    return true;
  const std::string_view cookies(req[http::field::cookie].data(), req[http::field::cookie].size());
  const auto cookie = cookie_value(cookies, "dojo_token");
  return !cookie.empty() && same_secret(percent_decoded(cookie), options.token);
}

void Server::Impl::accept() {
  acceptor.async_accept(net::make_strand(ioc), [this](beast::error_code ec, tcp::socket socket) {
    if (stopping) return;
    if (!ec && tls)
      std::make_shared<HttpConnection<beast::ssl_stream<beast::tcp_stream>>>(std::move(socket), *this)->run();
    else if (!ec)
      std::make_shared<HttpConnection<beast::tcp_stream>>(std::move(socket), *this)->run();
    accept();
  });
}

Server::Server(ServeOptions options, std::shared_ptr<ModelHost> host) : impl_(std::make_unique<Impl>()) {
  impl_->options = std::move(options);
  impl_->host = std::move(host);
  DOJO_CHECK(impl_->options.max_sessions >= 1, "serve: --max-sessions must be at least 1");
}

Server::~Server() { stop(); }

ServerMetrics& Server::metrics() { return impl_->metrics; }

uint16_t Server::start() {
  auto& s = *impl_;
  if (!s.options.study.empty()) s.study = std::make_unique<StudyApi>(s.options.study);
  s.study_pool.emplace(static_cast<size_t>(std::max(1, s.options.study_threads)));
  if (!s.options.tls_cert.empty() || !s.options.tls_key.empty()) {
    DOJO_CHECK(!s.options.tls_cert.empty() && !s.options.tls_key.empty(),
               "serve: HTTPS needs both --tls-cert and --tls-key");
    s.tls.emplace(net::ssl::context::tls_server);
    s.tls->set_options(net::ssl::context::default_workarounds | net::ssl::context::no_sslv2 |
                       net::ssl::context::no_sslv3 | net::ssl::context::no_tlsv1 |
                       net::ssl::context::no_tlsv1_1);
    beast::error_code ec;
    s.tls->use_certificate_chain_file(s.options.tls_cert.string(), ec);
    DOJO_CHECK(!ec, s.options.tls_cert.string() + ": not a PEM certificate chain: " + ec.message());
    s.tls->use_private_key_file(s.options.tls_key.string(), net::ssl::context::pem, ec);
    DOJO_CHECK(!ec, s.options.tls_key.string() +
                        ": not a PEM private key (or it does not match the certificate): " + ec.message());
  }
  beast::error_code ec;
  const auto address = net::ip::make_address(s.options.host, ec);
  DOJO_CHECK(!ec, "serve: --host '" + s.options.host + "' is not an IP address");
  DOJO_CHECK(address.is_loopback() || !s.options.token.empty() || s.options.insecure,
             "serve: --host " + s.options.host +
                 " opens the server to the network without a token: give --token (or --insecure to serve it "
                 "open anyway)");
  const tcp::endpoint endpoint(address, s.options.port);
  s.acceptor.open(endpoint.protocol(), ec);
  if (!ec) s.acceptor.set_option(net::socket_base::reuse_address(true), ec);
  if (!ec) s.acceptor.bind(endpoint, ec);
  if (!ec) s.acceptor.listen(net::socket_base::max_listen_connections, ec);
  DOJO_CHECK(!ec, "serve: cannot listen on " + s.options.host + ":" + std::to_string(s.options.port) + ": " +
                      ec.message());
  const auto port = s.acceptor.local_endpoint().port();  // before the IO threads share the acceptor
  s.keep_running.emplace(s.ioc.get_executor());
  s.accept();
  for (int i = 0; i < std::max(1, s.options.io_threads); ++i) s.threads.emplace_back([&s] { s.ioc.run(); });
  return port;
}

void Server::stop() {
  auto& s = *impl_;
  std::lock_guard<std::mutex> stop_lock(s.stop_mutex);
  if (s.stopped) return;
  s.stopping = true;
  // 1. No new connection: the listening socket closes on the strand its accept handlers run on, so
  //    after it no connection is made and the closers below are all there are. A request on a
  //    connection already open is answered 503 from now on.
  s.post_and_wait([&s](std::shared_ptr<void> running) {
    net::post(s.acceptor.get_executor(), [&s, running] {
      beast::error_code ec;
      s.acceptor.close(ec);
    });
  });
  // 2. Sessions close (their recordings are written); study requests already running finish and
  //    post their answers, rollout jobs answer 503 after the step they are in.
  s.close_connections(Server::Impl::ConnectionKind::kWebSocket);
  for (int waited = 0; s.sessions > 0 && waited < 300; ++waited)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  s.wait_for_background();
  // 3. Every HTTP connection left closes, then the IO threads stop.
  s.close_connections(Server::Impl::ConnectionKind::kHttp);
  s.keep_running.reset();
  s.ioc.stop();
  for (auto& t : s.threads)
    if (t.joinable()) t.join();
  s.threads.clear();
  if (s.study_pool) s.study_pool->join();
  // Work the IO threads started after the wait above (a WebSocket that finished closing winds its
  // session down on a thread of its own): none can start now, and none may outlive the server.
  s.wait_for_background();
  s.stopped = true;
}

}  // namespace dojo::serve
