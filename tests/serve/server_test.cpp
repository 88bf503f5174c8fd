// `dojo serve` over real sockets on loopback: health while loading, metrics, capabilities, the
// embedded page, tokens, malformed HTTP, live and step-by-step WebSocket sessions, the session
// cap, recordings and POST /v1/rollout. Models: the reference set (the post-trained teacher also
// streams as an undistilled "student"), start frames from a synthetic DojoSim-style dataset.
#include "serve/server.h"

#include <gtest/gtest.h>

#include <sys/wait.h>
#include <boost/asio/connect.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <boost/beast/websocket.hpp>

#include <cstdio>
#include <cstring>
#include <nlohmann/json.hpp>

#include "core/error.h"
#include "http_request.h"
#include "infer/generator.h"
#include "infer/world_model.h"
#include "io/jpeg.h"
#include "serve/model_host.h"
#include "serve/rollout_api.h"
#include "serve/session.h"
#include "sessions_drained.h"
#include "synthetic_data.h"
#include "test_util.h"

#include <chrono>
#include <thread>

namespace dojo::serve {
namespace {

namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
namespace net = boost::asio;
using tcp = net::ip::tcp;

using test::HttpResult;
// Requests to the server under test (tests/serve/http_request.h).
HttpResult request(uint16_t port, http::verb verb, const std::string& target, const std::string& body = "",
                   const std::string& bearer = "") {
  return test::http_request(port, verb, target, body, bearer);
}

class WsClient {
 public:
  explicit WsClient(uint16_t port) : ws_(ioc_) {
    beast::get_lowest_layer(ws_).connect(tcp::endpoint(net::ip::make_address("127.0.0.1"), port));
    ws_.handshake("127.0.0.1", "/ws");
  }
  void send(const nlohmann::json& j) {
    ws_.text(true);
    ws_.write(net::buffer(j.dump()));
  }
  void send_raw(const std::string& text) {
    ws_.text(true);
    ws_.write(net::buffer(text));
  }
  // The next message: text as JSON (binary: {"binary": size}), frames collected in `frames`.
  nlohmann::json next() {
    beast::flat_buffer buffer;
    ws_.read(buffer);
    const auto data = beast::buffers_to_string(buffer.data());
    if (ws_.got_text()) return nlohmann::json::parse(data);
    frames.push_back(data);
    return {{"binary", data.size()}};
  }
  // Reads until a text message of `type` arrives (frames on the way are kept).
  nlohmann::json until(const std::string& type, int limit = 400) {
    for (int i = 0; i < limit; ++i) {
      const auto m = next();
      if (m.contains("type") && m["type"] == type) return m;
      if (m.contains("type") && m["type"] == "error" && type != "error") ADD_FAILURE() << m.dump();
    }
    ADD_FAILURE() << "no '" << type << "' message";
    return {};
  }
  size_t frames_until(size_t n) {
    while (frames.size() < n) next();
    return frames.size();
  }
  std::vector<std::string> frames;

 private:
  net::io_context ioc_;
  websocket::stream<beast::tcp_stream> ws_;
};

uint32_t frame_seq(const std::string& frame) {
  uint32_t seq = 0;
  std::memcpy(&seq, frame.data() + 4, 4);
  return seq;
}

class ServeTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    tmp_ = new test::TempDir();
    test::SyntheticOptions g;
    g.episodes = 2;
    g.frames = 16;
    g.size = 64;
    g.val_episodes = 2;
    test::write_synthetic_dataset(*tmp_ / "robot", g);
  }
  static void TearDownTestSuite() {
    delete tmp_;
    tmp_ = nullptr;
  }
  // The reference set's post-trained model as both "student" and "teacher" (the teacher sampling
  // with `teacher_steps` a chunk, 0: its trained sampler's).
  static std::shared_ptr<ModelHost> host(bool load = true, int teacher_steps = 0) {
    const auto reference = std::filesystem::path(DOJO_SOURCE_DIR) / "models" / "reference";
    ModelHost::Options o;
    ModelSpec student;
    student.name = "student";
    student.checkpoint = reference / "wm_posttrain";
    student.tokenizer = reference / "tokenizer";
    ModelSpec teacher = student;
    teacher.name = "teacher";
    teacher.streaming = false;
    teacher.teacher_steps = teacher_steps;
    o.models = {student, teacher};
    o.data = *tmp_ / "robot";
    auto h = std::make_shared<ModelHost>(o);
    if (load) h->load();
    return h;
  }
  static ServeOptions options() {
    ServeOptions o;
    o.port = 0;
    o.fps = 40;
    o.recordings = *tmp_ / "recordings";
    return o;
  }
  static test::TempDir* tmp_;
};
test::TempDir* ServeTest::tmp_ = nullptr;

TEST(ServeCodecs, Base64AndJpegRoundTrip) {
  // RFC 4648 §10 test vectors.
  const std::vector<std::pair<std::string, std::string>> vectors = {{"", ""},
                                                                    {"f", "Zg=="},
                                                                    {"fo", "Zm8="},
                                                                    {"foo", "Zm9v"},
                                                                    {"foob", "Zm9vYg=="},
                                                                    {"fooba", "Zm9vYmE="},
                                                                    {"foobar", "Zm9vYmFy"}};
  for (const auto& [plain, coded] : vectors) {
    EXPECT_EQ(base64_encode(plain), coded);
    EXPECT_EQ(base64_decode(coded, "x"), plain);
  }
  EXPECT_THROW(base64_decode("Zm9", "x"), Error);
  EXPECT_THROW(base64_decode("Zm!v", "x"), Error);

  auto frame = torch::zeros({32, 48, 3}, torch::kByte);
  frame.narrow(1, 0, 24).fill_(200);  // half bright, half dark
  const auto decoded = io::decode_jpeg(io::encode_jpeg(frame, 95));
  ASSERT_EQ(decoded.sizes(), frame.sizes());
  EXPECT_LT((decoded.to(torch::kFloat) - frame.to(torch::kFloat)).abs().mean().item<double>(), 3.0);
  EXPECT_THROW(io::decode_jpeg("not a jpeg", "upload"), Error);
  try {
    io::decode_jpeg("\xff\xd8\xff garbage", "upload");
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("upload"), std::string::npos);
  }
}

// A hosted teacher samples its chunks with the steps it was given (`serve --teacher-steps`).
TEST_F(ServeTest, HostedTeacherSamplesWithItsSteps) {
  test::OneThread one;
  const auto reference = std::filesystem::path(DOJO_SOURCE_DIR) / "models" / "reference";
  auto model = infer::WorldModel::load(reference / "wm_posttrain", reference / "tokenizer");
  const auto first = torch::randint(0, 255, {64, 64, 3}, torch::kByte);
  const auto actions = torch::rand({12, 384}) * 2 - 1;
  const auto hosted = host(/*load=*/true, /*teacher_steps=*/2);  // outlives its generators
  auto served = hosted->make_generator("teacher");
  auto direct = infer::make_teacher_generator(model, nullptr, 2);
  served->reset(first, 3);
  direct->reset(first, 3);
  EXPECT_TRUE(served->step(actions).equal(direct->step(actions)));
}

TEST_F(ServeTest, HttpRoutesTokensAndMalformedRequests) {
  test::OneThread one;
  auto h = host(/*load=*/false);
  auto o = options();
  o.token = "secret";
  Server server(o, h);
  const auto port = server.start();
  EXPECT_EQ(request(port, http::verb::get, "/health").status, 503) << "models not loaded yet";
  h->load();
  EXPECT_EQ(request(port, http::verb::get, "/health").status, 200);
  EXPECT_EQ(request(port, http::verb::get, "/api/capabilities").status, 401);
  auto caps = request(port, http::verb::get, "/api/capabilities", "", "secret");
  ASSERT_EQ(caps.status, 200);
  const auto j = nlohmann::json::parse(caps.body);
  EXPECT_EQ(j.at("models").size(), 2u);
  EXPECT_EQ(j.at("models")[0].at("action_slots")[0].at("slot"), "dojosim_robot");
  EXPECT_EQ(j.at("episodes").size(), 2u);
  // Never in the URL (addresses reach logs and histories); the page's cookie, set from the
  // address's fragment, or a Bearer header.
  const auto in_url = request(port, http::verb::get, "/api/capabilities?token=secret");
  EXPECT_EQ(in_url.status, 401);
  EXPECT_NE(in_url.body.find("never in the URL"), std::string::npos) << in_url.body;
  EXPECT_EQ(
      test::http_request(port, http::verb::get, "/api/capabilities", "", "", "lang=en; dojo_token=secret")
          .status,
      200);
  EXPECT_EQ(test::http_request(port, http::verb::get, "/api/capabilities", "", "", "dojo_token=secre").status,
            401);
  EXPECT_EQ(
      test::http_request(port, http::verb::get, "/api/capabilities", "", "", "dojo_token=secretX").status,
      401);
  EXPECT_EQ(request(port, http::verb::get, "/api/capabilities", "", "secre").status, 401);
  const auto page = request(port, http::verb::get, "/");
  EXPECT_EQ(page.status, 200);
  EXPECT_NE(page.body.find("teleop.js"), std::string::npos);
  // The pages and scripts load without the token (a browser fetches scripts without it); what
  // they call does not.
  EXPECT_EQ(request(port, http::verb::get, "/teleop.js").status, 200);
  EXPECT_EQ(request(port, http::verb::get, "/dojosim_robot.mapping.json").status, 200);
  EXPECT_EQ(request(port, http::verb::get, "/study/clips/x.mp4").status, 401);
  EXPECT_EQ(request(port, http::verb::post, "/v1/rollout", "{}").status, 401);
  EXPECT_EQ(request(port, http::verb::get, "/nowhere", "", "secret").status, 404);
  EXPECT_EQ(request(port, http::verb::post, "/v1/rollout", "{not json", "secret").status, 400);

  // Raw garbage instead of HTTP: answered 400 (or dropped), and the server keeps serving.
  {
    net::io_context ioc;
    tcp::socket s(ioc);
    s.connect(tcp::endpoint(net::ip::make_address("127.0.0.1"), port));
    net::write(s, net::buffer(std::string("\x01\x02 GARBAGE / HTTP/9\r\n\r\n")));
    std::string reply(64, '\0');
    beast::error_code ec;
    const auto n = s.read_some(net::buffer(reply), ec);
    if (!ec) {
      EXPECT_NE(reply.substr(0, n).find("400"), std::string::npos);
    }
  }
  EXPECT_EQ(request(port, http::verb::get, "/health").status, 200);
  const auto metrics = request(port, http::verb::get, "/metrics", "", "secret");
  EXPECT_NE(metrics.body.find("dojo_step_seconds_bucket{le=\"+Inf\"}"), std::string::npos);
  EXPECT_NE(metrics.body.find("dojo_errors_total"), std::string::npos);
  server.stop();

  // Another host than loopback needs a token, or --insecure.
  auto open = options();
  open.host = "0.0.0.0";
  Server exposed(open, h);
  EXPECT_NE(test::error_message([&] { exposed.start(); })
                .find("--host 0.0.0.0 opens the server to the network "
                      "without a token"),
            std::string::npos);
  open.insecure = true;
  Server insecure(open, h);
  EXPECT_GT(insecure.start(), 0);
  insecure.stop();
}

TEST_F(ServeTest, LiveSessionStreamsFramesAndSurvivesBadMessages) {
  test::OneThread one;
  Server server(options(), host());
  const auto port = server.start();
  WsClient ws(port);
  ws.send_raw("{oops");
  EXPECT_EQ(ws.until("error")["message"], "message is not valid JSON");
  ws.send({{"type", "warp"}});
  EXPECT_NE(ws.until("error")["message"].get<std::string>().find("unknown message type"), std::string::npos);
  ws.send({{"type", "control"}, {"velocity", {1, 0, 0, 0, 0, 0}}});
  EXPECT_NE(ws.until("error")["message"].get<std::string>().find("start a session"), std::string::npos);

  ws.send({{"type", "start"}, {"mode", "live"}, {"model", "student"}});
  const auto ready = ws.until("ready");
  EXPECT_EQ(ready["width"], 64);
  EXPECT_EQ(ready["command"].size(), 6u);
  ws.send({{"type", "control"}, {"velocity", {1, 2}}});  // wrong width: an error, the stream goes on
  EXPECT_NE(ws.until("error")["message"].get<std::string>().find("6 numbers"), std::string::npos);
  ws.send({{"type", "control"}, {"velocity", {0.8, 0, 0, 0, 0, 0}}, {"t", 12.5}});
  // Frames already queued when the control arrived still echo the old time; from the first frame
  // it drove on, every frame carries 12.5. A stalled machine may queue more, so read until then.
  const size_t sent_at = ws.frames.size();
  double echoed = 0;
  for (size_t wanted = sent_at + 1; wanted <= sent_at + 60 && echoed != 12.5; ++wanted) {
    ws.frames_until(wanted);
    ASSERT_GT(ws.frames.back().size(), Session::kFrameHeaderBytes);
    std::memcpy(&echoed, ws.frames.back().data() + 16, 8);
  }
  const auto& last = ws.frames.back();
  EXPECT_EQ(last.substr(0, 4), "DJF1");
  EXPECT_EQ(echoed, 12.5) << "the control's client time comes back with the frames it drove";
  EXPECT_GT(frame_seq(last), frame_seq(ws.frames.front()));
  const auto image = io::decode_jpeg(std::string_view(last).substr(Session::kFrameHeaderBytes));
  EXPECT_EQ(image.sizes(), (std::vector<int64_t>{64, 64, 3}));

  // A recording: start, a few frames, stop -> a complete directory under its final name.
  ws.send({{"type", "record"}, {"on", true}});
  ws.until("recording");
  ws.frames_until(ws.frames.size() + 8);
  ws.send({{"type", "record"}, {"on", false}});
  const auto recorded = std::filesystem::path(ws.until("recorded")["path"].get<std::string>());
  EXPECT_TRUE(std::filesystem::exists(recorded / "video.mp4"));
  EXPECT_TRUE(std::filesystem::exists(recorded / "start.jpg"));
  EXPECT_GT(test::read_file(recorded / "actions.jsonl").size(), 0u);
  const auto about = nlohmann::json::parse(test::read_file(recorded / "session.json"));
  EXPECT_GT(about["first_step"].get<int>(), 0) << "begun mid-stream: not replayable, and it says so";
  EXPECT_EQ(about["model"], "student");
  EXPECT_FALSE(about["episode"].get<std::string>().empty());

  // Recorded from the start: the recording begins at step 0, so the session can be replayed.
  ws.send({{"type", "start"}, {"mode", "live"}, {"model", "student"}, {"record", true}});
  ws.until("recording");
  ws.frames_until(ws.frames.size() + 8);
  ws.send({{"type", "record"}, {"on", false}});
  const auto from_start = std::filesystem::path(ws.until("recorded")["path"].get<std::string>());
  EXPECT_EQ(nlohmann::json::parse(test::read_file(from_start / "session.json"))["first_step"], 0);
  // On and off back to back, while the worker computes a step: the off used to replace the on
  // before the worker saw it, and the page waited for a "recorded" that never came.
  ws.send({{"type", "record"}, {"on", true}});
  ws.send({{"type", "record"}, {"on", false}});
  ws.until("recording");
  const auto quick = std::filesystem::path(ws.until("recorded")["path"].get<std::string>());
  EXPECT_TRUE(std::filesystem::exists(quick / "video.mp4"));
  ws.send({{"type", "start"}, {"record", 1}});
  EXPECT_NE(ws.until("error")["message"].get<std::string>().find("'record' must be true or false"),
            std::string::npos);
  server.stop();
}

TEST_F(ServeTest, StepModeRolloutApiAndSessionCap) {
  test::OneThread one;
  auto o = options();
  o.max_sessions = 1;
  Server server(o, host());
  const auto port = server.start();
  {
    WsClient ws(port);
    ws.send({{"type", "start"}, {"mode", "step"}, {"model", "student"}});
    EXPECT_EQ(ws.until("ready")["actions_per_step"], 4);
    ws.frames_until(1);  // the start frame follows "ready"
    // The cap: a second session is refused with 503 while this one lives.
    EXPECT_THROW(WsClient second(port), boost::system::system_error);
    const nlohmann::json raw_rows = {{1, 0.5, 1.8, 0.8, 0, 0.5},
                                     {1, 0.5, 1.8, 0.8, 0, 0.5},
                                     {1.1, 0.5, 1.8, 0.8, 0, 0.5},
                                     {1.2, 0.5, 1.8, 0.8, 0, 0.5}};
    const size_t before = ws.frames.size();
    ws.send({{"type", "step"}, {"actions", raw_rows}});
    EXPECT_EQ(ws.until("step_done")["frames"], 4);
    EXPECT_EQ(ws.frames.size(), before + 4) << "step mode loses no frame";
    ws.send({{"type", "step"}, {"actions", {{1, 2, 3}}}});
    EXPECT_NE(ws.until("error")["message"].get<std::string>().find("4 actions per step"), std::string::npos);
  }
  ASSERT_TRUE(test::sessions_drained(server)) << "the cap of 1 needs the closed session freed";

  nlohmann::json body = {{"model", "student"}, {"format", "jpeg"}, {"actions", nlohmann::json::array()}};
  for (int i = 0; i < 8; ++i) body["actions"].push_back({1 + 0.02 * i, 0.5, 1.8, 0.8, 0, 0.5});
  auto r = request(port, http::verb::post, "/v1/rollout", body.dump());
  ASSERT_EQ(r.status, 200) << r.body;
  EXPECT_EQ(nlohmann::json::parse(r.body).at("frames").size(), 9u) << "the start frame and 8 more";
  body["format"] = "mp4";
  r = request(port, http::verb::post, "/v1/rollout", body.dump());
  ASSERT_EQ(r.status, 200) << r.body;
  EXPECT_EQ(r.content_type, "video/mp4");
  EXPECT_EQ(r.body.substr(4, 4), "ftyp");
  body["actions"] = {{1, 2, 3}};
  r = request(port, http::verb::post, "/v1/rollout", body.dump());
  EXPECT_EQ(r.status, 400);
  EXPECT_NE(r.body.find("'actions'"), std::string::npos) << r.body;
  server.stop();

  // Bounded by frames (before any work) and by time (between steps), not only by the body's size.
  auto bounded = options();
  bounded.max_rollout_frames = 8;
  const auto shared = host();
  Server small(bounded, shared);
  const auto small_port = small.start();
  body["actions"] = nlohmann::json::array();
  for (int i = 0; i < 8; ++i) body["actions"].push_back({1 + 0.02 * i, 0.5, 1.8, 0.8, 0, 0.5});
  r = request(small_port, http::verb::post, "/v1/rollout", body.dump());
  EXPECT_EQ(r.status, 413);
  EXPECT_NE(r.body.find("8 rows ask for 9 frames; this server makes at most 8"), std::string::npos) << r.body;
  small.stop();
  bounded.max_rollout_frames = 1200;
  bounded.max_rollout_seconds = 1e-9;
  Server hasty(bounded, shared);
  const auto hasty_port = hasty.start();
  r = request(hasty_port, http::verb::post, "/v1/rollout", body.dump());
  EXPECT_EQ(r.status, 503);
  EXPECT_NE(r.body.find("--max-rollout-seconds"), std::string::npos) << r.body;
  EXPECT_EQ(request(hasty_port, http::verb::get, "/health").status, 200) << "and it keeps serving";
  hasty.stop();

  // A server stopped under a long rollout waits for the step in flight, not the whole rollout:
  // the rollout answers 503, saying how far it got.
  Server busy(options(), shared);
  const auto busy_port = busy.start();
  body["actions"] = nlohmann::json::array();
  for (int i = 0; i < 1196; ++i) body["actions"].push_back({1 + 0.0002 * i, 0.5, 1.8, 0.8, 0, 0.5});
  HttpResult long_rollout;
  std::thread client(
      [&] { long_rollout = request(busy_port, http::verb::post, "/v1/rollout", body.dump()); });
  // Stop once the rollout has generated frames (the counter past the start frame's).
  const auto started = std::chrono::steady_clock::now();
  auto frames_generated = [&] {
    const auto text = request(busy_port, http::verb::get, "/metrics").body;
    const std::string key = "\ndojo_frames_generated_total ";
    const auto at = text.find(key);
    return at == std::string::npos ? 0.0 : std::stod(text.substr(at + key.size()));
  };
  while (frames_generated() < 8 && std::chrono::steady_clock::now() - started < std::chrono::seconds(60))
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  const auto stop_start = std::chrono::steady_clock::now();
  busy.stop();
  const double stop_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - stop_start).count();
  client.join();
  EXPECT_EQ(long_rollout.status, 503) << long_rollout.body;
  EXPECT_NE(long_rollout.body.find("the server is stopping (after "), std::string::npos) << long_rollout.body;
  EXPECT_LT(stop_seconds, 5) << "the rollout had 299 steps to go";
}

}  // namespace
}  // namespace dojo::serve

namespace dojo::serve {
namespace {

// examples/step_client.py (standard-library Python) drives a step-mode session end to end, and a
// server-side error becomes its one-line message and a non-zero exit.
TEST_F(ServeTest, PythonStepClientDrivesTheModel) {
  Server server(options(), host());
  const auto port = server.start();
  const auto client = std::filesystem::path(DOJO_SOURCE_DIR) / "examples" / "step_client.py";
  const auto out = *tmp_ / "python_frames";
  const auto run = [&](const std::string& args) {
    return test::run_command("python3 " + client.string() + " --url ws://127.0.0.1:" + std::to_string(port) +
                             "/ws " + args);
  };
  const auto [status, output] = run("--model student --steps 2 --out " + out.string());
  ASSERT_EQ(status, 0) << output;
  const auto summary = nlohmann::json::parse(output.substr(output.rfind('{')));
  EXPECT_EQ(summary["steps"], 2);
  EXPECT_EQ(summary["frames"], 9);  // the start frame and 4 per step
  EXPECT_EQ(summary["last_seq"], 8);
  for (int i = 0; i < 9; ++i) {
    char name[32];
    std::snprintf(name, sizeof name, "frame_%05d.jpg", i);
    const auto jpeg = test::read_file(out / name);
    ASSERT_FALSE(jpeg.empty()) << name;
    EXPECT_EQ(io::decode_jpeg(jpeg, name).size(0), 64);
  }
  const auto refused = run("--model nonesuch --steps 1");
  EXPECT_NE(refused.exit_code, 0);
  EXPECT_NE(refused.output.find("unknown model 'nonesuch'"), std::string::npos) << refused.output;
  server.stop();
}

}  // namespace
}  // namespace dojo::serve
