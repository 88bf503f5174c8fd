// The preference study (serve/study.h): study.json checks, trial order and placement, SQLite votes
// (duplicates refused, concurrent raters lose nothing), win rates and Wilson intervals, the study's
// routes over HTTP and over HTTPS (a study server needs no model, so these tests load none).
#include "serve/study.h"

#include <gtest/gtest.h>

#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/ssl.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <boost/beast/ssl.hpp>
#include <boost/beast/websocket.hpp>
#include <boost/beast/websocket/ssl.hpp>
#include <fstream>
#include <set>
#include <thread>

#include "core/error.h"
#include "http_request.h"
#include "io/video.h"
#include "serve/model_host.h"
#include "serve/server.h"
#include "serve/study_api.h"
#include "serve/study_create.h"
#include "test_util.h"

namespace dojo::serve {
namespace {

namespace beast = boost::beast;
namespace http = beast::http;
namespace net = boost::asio;
using tcp = net::ip::tcp;

void expect_error_contains(const std::function<void()>& fn, const std::string& text) {
  const auto message = test::error_message(fn);
  EXPECT_NE(message.find(text), std::string::npos) << message;
}

// SOURCE/ID/{truth,a,b}.mp4 for `items` items: tiny clips, enough for the study's file checks.
std::filesystem::path write_clips(const std::filesystem::path& source, int items) {
  for (int i = 0; i < items; ++i) {
    const auto dir = source / ("ep-" + std::to_string(i));
    std::filesystem::create_directories(dir);
    for (const auto* name : {"truth", "a", "b", "c"})
      io::write_video((dir / (std::string(name) + ".mp4")).string(),
                      torch::full({3, 16, 16, 3}, (40 * i + 10) % 250, torch::kUInt8));
  }
  return source;
}

TEST(Study, WilsonIntervalMatchesKnownValues) {
  // p = 0.5, n = 100: 0.4038 .. 0.5962; p = 0, n = 10: 0 .. 0.2775 (Wilson 1927; standard tables).
  auto [low, high] = wilson_interval(0.5, 100);
  EXPECT_NEAR(low, 0.4038, 1e-4);
  EXPECT_NEAR(high, 0.5962, 1e-4);
  std::tie(low, high) = wilson_interval(0.0, 10);
  EXPECT_NEAR(low, 0.0, 1e-9);
  EXPECT_NEAR(high, 0.2775, 1e-4);
  std::tie(low, high) = wilson_interval(0.5, 0);
  EXPECT_EQ(low, 0.0);
  EXPECT_EQ(high, 1.0);
}

TEST(Study, CreateFromVideosAndCheckFiles) {
  test::TempDir tmp;
  const auto source = write_clips(tmp / "clips", 2);
  const auto study = create_study_from_videos(tmp / "s", source, {"a", "b", "c"}, "demo");
  EXPECT_EQ(study.items.size(), 2u);
  EXPECT_EQ(study.trials().size(), 6u);  // 2 items x 3 pairs
  EXPECT_EQ(Study::open(tmp / "s").models, (std::vector<std::string>{"a", "b", "c"}));
  // Only the study's own clips can be reached.
  EXPECT_FALSE(study.clip("videos/000/a.mp4").empty());
  EXPECT_TRUE(study.clip("study.json").empty());
  EXPECT_TRUE(study.clip("videos/000/../../study.json").empty());
  // Bad inputs name the file or field.
  expect_error_contains([&] { create_study_from_videos(tmp / "t", source, {"a", "zzz"}, ""); }, "zzz.mp4");
  expect_error_contains([&] { create_study_from_videos(tmp / "t", source, {"a"}, ""); }, "at least two");
  std::filesystem::remove(tmp / "s" / "videos" / "001" / "b.mp4");
  expect_error_contains([&] { Study::open(tmp / "s"); }, "missing clip");
  std::ofstream(tmp / "s" / "study.json") << R"({"format": "dojo-study-1", "models": ["a"]})";
  expect_error_contains([&] { Study::open(tmp / "s"); }, "'models'");
}

TEST(Study, RaterOrderAndPlacementAreFixedPerRaterAndBalanced) {
  test::TempDir tmp;
  const auto study = create_study_from_videos(tmp / "s", write_clips(tmp / "clips", 4), {"a", "b"}, "");
  const auto order = study.trials_for("rater-1");
  ASSERT_EQ(order.size(), 4u);
  EXPECT_EQ(study.trials_for("rater-1")[0].id, order[0].id);
  std::set<std::string> ids;
  for (const auto& t : order) ids.insert(t.id);
  EXPECT_EQ(ids.size(), 4u);  // a permutation
  int left_a = 0, total = 0;
  for (int r = 0; r < 200; ++r)
    for (const auto& t : study.trials()) {
      left_a += study.left_model("r" + std::to_string(r), t) == "a";
      ++total;
    }
  EXPECT_NEAR(static_cast<double>(left_a) / total, 0.5, 0.06);
  // Within one rater too: over 20 items (ids of both parities) model a is not always on one side.
  const auto many = create_study_from_videos(tmp / "m", write_clips(tmp / "many", 20), {"a", "b"}, "");
  for (const auto* rater : {"r1", "r2", "r3"}) {
    int left = 0;
    for (const auto& t : many.trials()) left += many.left_model(rater, t) == "a";
    EXPECT_GT(left, 3) << rater;
    EXPECT_LT(left, 17) << rater;
  }
}

TEST(Study, VotesAreStoredOnceAndReportedPerPair) {
  test::TempDir tmp;
  const auto study = create_study_from_videos(tmp / "s", write_clips(tmp / "clips", 2), {"a", "b"}, "");
  VoteStore votes(tmp / "s" / "votes.sqlite");
  const auto r1 = votes.new_rater("test"), r2 = votes.new_rater("test");
  EXPECT_NE(r1, r2);
  EXPECT_TRUE(votes.has_rater(r1));
  EXPECT_FALSE(votes.has_rater("nobody"));
  const auto trials = study.trials();
  const auto vote = [&](const std::string& rater, const StudyTrial& t, const std::string& left,
                        const std::string& physics, const std::string& action) {
    return votes.add({{rater, t.id, t.item->id, t.model_a, t.model_b, left, "physics", physics},
                      {rater, t.id, t.item->id, t.model_a, t.model_b, left, "action", action}});
  };
  EXPECT_TRUE(vote(r1, trials[0], "a", "left", "tie"));      // a wins physics
  EXPECT_FALSE(vote(r1, trials[0], "a", "right", "right"));  // the same trial again: refused
  EXPECT_TRUE(vote(r1, trials[1], "b", "left", "right"));    // b wins physics, a wins action
  EXPECT_TRUE(vote(r2, trials[0], "b", "right", "left"));    // a wins physics, b wins action
  EXPECT_EQ(votes.answered(r1).size(), 2u);
  const auto report = make_report(study, votes.all());
  EXPECT_EQ(report.raters, 2);
  EXPECT_EQ(report.votes, 6);
  ASSERT_EQ(report.pairs.size(), 2u);
  const auto& physics = report.pairs[0];
  EXPECT_EQ(physics.question, "physics");
  EXPECT_EQ(physics.a_wins, 2);
  EXPECT_EQ(physics.b_wins, 1);
  EXPECT_EQ(physics.left_chosen, 2);
  EXPECT_NEAR(physics.win_rate_a(), 2.0 / 3, 1e-12);
  const auto& action = report.pairs[1];
  EXPECT_EQ(action.a_wins, 1);
  EXPECT_EQ(action.b_wins, 1);
  EXPECT_EQ(action.ties, 1);
  EXPECT_NEAR(action.win_rate_a(), 0.5, 1e-12);
  EXPECT_NE(report.to_markdown().find("| physics | 66.7% ["), std::string::npos) << report.to_markdown();
  EXPECT_NE(report.to_html().find("a &gt; b"), std::string::npos);
  EXPECT_EQ(report.to_json()["pairs"][0]["n"], 3);
}

TEST(Study, ConcurrentRatersLoseNoVote) {
  test::TempDir tmp;
  const auto study = create_study_from_videos(tmp / "s", write_clips(tmp / "clips", 3), {"a", "b", "c"}, "");
  StudyApi api(tmp / "s");
  constexpr int kRaters = 6;
  std::vector<std::thread> threads;
  std::atomic<int> stored{0};
  for (int r = 0; r < kRaters; ++r)
    threads.emplace_back([&] {
      const auto rater =
          nlohmann::json::parse(api.handle("POST", "/api/study/raters", "", "", "t").body)["rater"]
              .get<std::string>();
      for (int guard = 0; guard < 100; ++guard) {  // 9 trials; a vote that never lands must not hang
        const auto next = nlohmann::json::parse(api.handle("GET", "/api/study/next", rater, "", "t").body);
        if (next["done"]) break;
        const nlohmann::json body = {{"rater", rater},
                                     {"trial", next["trial"]},
                                     {"answers", {{"physics", "left"}, {"action", "right"}}}};
        if (api.handle("POST", "/api/study/vote", "", body.dump(), "t").status == 200) ++stored;
      }
    });
  for (auto& t : threads) t.join();
  EXPECT_EQ(stored, kRaters * 9);  // 3 items x 3 pairs each
  // A second handle on the same file (the report, another process) sees every vote.
  VoteStore reader(tmp / "s" / "votes.sqlite");
  EXPECT_EQ(reader.all().size(), static_cast<size_t>(kRaters * 9 * 2));
  EXPECT_EQ(make_report(study, reader.all()).raters, kRaters);
}

TEST(Study, ApiAnswersBadInputWithErrors) {
  test::TempDir tmp;
  create_study_from_videos(tmp / "s", write_clips(tmp / "clips", 1), {"a", "b"}, "");
  StudyApi api(tmp / "s");
  const auto rater = nlohmann::json::parse(api.handle("POST", "/api/study/raters", "", "", "").body)["rater"];
  const auto expect = [&](const std::string& method, const std::string& path, const std::string& q,
                          const std::string& body, int status, const std::string& text) {
    const auto r = api.handle(method, path, q, body, "");
    EXPECT_EQ(r.status, status) << path << " " << body << " -> " << r.body;
    EXPECT_NE(r.body.find(text), std::string::npos) << r.body;
  };
  expect("GET", "/api/study/next", "nobody", "", 400, "unknown rater");
  expect("GET", "/api/study/raters", "", "", 405, "POST");
  expect("POST", "/api/study/vote", "", "{not json", 400, "JSON object");
  expect("POST", "/api/study/vote", "", nlohmann::json{{"rater", rater}, {"trial", 3}}.dump(), 400,
         "'trial'");
  expect("POST", "/api/study/vote", "",
         nlohmann::json{{"rater", rater}, {"trial", "x"}, {"answers", {}}}.dump(), 400, "no trial 'x'");
  const auto trial = nlohmann::json::parse(api.handle("GET", "/api/study/next", rater, "", "").body)["trial"];
  expect(
      "POST", "/api/study/vote", "",
      nlohmann::json{{"rater", rater}, {"trial", trial}, {"answers", {{"physics", "A"}, {"action", "tie"}}}}
          .dump(),
      400, "answers.physics");
  expect("POST", "/api/study/vote", "",
         nlohmann::json{{"rater", rater}, {"trial", trial}, {"answers", {{"physics", "tie"}}}}.dump(), 400,
         "answers.action");
  expect("GET", "/study/clips/../study.json", "", "", 404, "no clip");
  expect("GET", "/study/clips/videos/000/a.mp4", "", "", 200, "");
  expect(
      "POST", "/api/study/vote", "",
      nlohmann::json{{"rater", rater}, {"trial", trial}, {"answers", {{"physics", "tie"}, {"action", "tie"}}}}
          .dump(),
      200, "\"stored\":true");
  expect("GET", "/api/study/next", rater, "", 200, "\"done\":true");
}

// HTTPS with the committed self-signed test certificate: routes answer over TLS, a WebSocket
// session runs over WSS, plain HTTP to the TLS port gets nothing and the server goes on.
TEST(Study, ServedOverHttpsAndWss) {
  test::TempDir tmp;
  create_study_from_videos(tmp / "s", write_clips(tmp / "clips", 1), {"a", "b"}, "");
  auto host = std::make_shared<ModelHost>(ModelHost::Options{});  // a study server: no model
  host->load();
  ServeOptions o;
  o.port = 0;
  o.study = tmp / "s";
  const auto tls = std::filesystem::path(DOJO_SOURCE_DIR) / "tests" / "serve" / "tls";
  o.tls_cert = tls / "test_cert.pem";
  o.tls_key = tls / "test_key.pem";
  Server server(o, host);
  const auto port = server.start();
  const tcp::endpoint endpoint(net::ip::make_address("127.0.0.1"), port);

  net::ssl::context client(net::ssl::context::tls_client);
  client.set_verify_mode(net::ssl::verify_none);  // self-signed
  const auto https = [&](http::verb verb, const std::string& target) {
    net::io_context ioc;
    beast::ssl_stream<beast::tcp_stream> stream(ioc, client);
    beast::get_lowest_layer(stream).connect(endpoint);
    stream.handshake(net::ssl::stream_base::client);
    http::request<http::string_body> req{verb, target, 11};
    req.set(http::field::host, "127.0.0.1");
    req.prepare_payload();
    http::write(stream, req);
    beast::flat_buffer buffer;
    http::response<http::string_body> res;
    http::read(stream, buffer, res);
    return std::make_pair(static_cast<int>(res.result_int()), res.body());
  };
  {  // plain HTTP on the TLS port: the handshake fails, the connection closes
    net::io_context ioc;
    beast::tcp_stream stream(ioc);
    stream.connect(endpoint);
    http::request<http::string_body> req{http::verb::get, "/health", 11};
    http::write(stream, req);
    beast::flat_buffer buffer;
    http::response<http::string_body> res;
    beast::error_code ec;
    http::read(stream, buffer, res, ec);
    EXPECT_TRUE(ec);
  }
  EXPECT_EQ(https(http::verb::get, "/health").first, 200);
  EXPECT_NE(https(http::verb::get, "/study").second.find("study.js"), std::string::npos);
  const auto rater = https(http::verb::post, "/api/study/raters");
  EXPECT_EQ(rater.first, 200);
  EXPECT_NE(https(http::verb::get,
                  "/api/study/next?rater=" + nlohmann::json::parse(rater.second)["rater"].get<std::string>())
                .second.find("\"trial\""),
            std::string::npos);

  net::io_context ioc;
  beast::websocket::stream<beast::ssl_stream<beast::tcp_stream>> ws(ioc, client);
  beast::get_lowest_layer(ws).connect(endpoint);
  ws.next_layer().handshake(net::ssl::stream_base::client);
  ws.handshake("127.0.0.1", "/ws");
  ws.text(true);
  ws.write(net::buffer(std::string(R"({"type":"start","mode":"step"})")));
  beast::flat_buffer buffer;
  ws.read(buffer);
  const auto reply = nlohmann::json::parse(beast::buffers_to_string(buffer.data()));
  EXPECT_EQ(reply["type"], "error");
  EXPECT_NE(reply["message"].get<std::string>().find("hosts no model"), std::string::npos) << reply.dump();
  ws.close(beast::websocket::close_code::normal);
  server.stop();

  ServeOptions bad = o;
  bad.tls_key = tls / "missing.pem";
  Server broken(bad, host);
  expect_error_contains([&] { broken.start(); }, "missing.pem");
}

}  // namespace
}  // namespace dojo::serve

namespace dojo::serve {
namespace {

int process_threads() {
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line))
    if (line.rfind("Threads:", 0) == 0) return std::stoi(line.substr(8));
  return -1;
}

// A crowd of voters against a server whose study runs on 2 threads with at most 4 requests queued
// or running: every request is answered (a vote or 503, retried), no thread is started per request,
// and the votes stored are exactly the votes answered 200.
TEST(Study, ACrowdOfVotersIsAnsweredOnABoundedPoolAndLosesNoVote) {
  test::TempDir tmp;
  create_study_from_videos(tmp / "s", write_clips(tmp / "clips", 2), {"a", "b"}, "");
  auto host = std::make_shared<ModelHost>(ModelHost::Options{});  // a study server: no model
  host->load();
  ServeOptions o;
  o.port = 0;
  o.study = tmp / "s";
  o.study_threads = 2;
  o.max_study_requests = 4;
  Server server(o, host);
  const auto port = server.start();
  constexpr int kVoters = 24;
  std::atomic<bool> sampling{true};
  std::atomic<int> peak{0};
  std::thread sampler([&] {
    while (sampling)
      peak = std::max(peak.load(), process_threads()),
      std::this_thread::sleep_for(std::chrono::microseconds(300));
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  const int before = process_threads();  // the server's threads, the pool's and the sampler
  std::atomic<int> stored{0}, busy{0}, failed{0};
  const auto call = [&](http::verb verb, const std::string& target, const std::string& body) {
    for (int attempt = 0; attempt < 400; ++attempt) {
      const auto r = test::http_request(port, verb, target, body);
      if (r.status != 503) return r;
      ++busy;
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    return test::HttpResult{503, "", ""};
  };
  std::vector<std::thread> voters;
  for (int v = 0; v < kVoters; ++v)
    voters.emplace_back([&] {
      const auto made = call(http::verb::post, "/api/study/raters", "");
      if (made.status != 200) return void(++failed);
      const auto rater = nlohmann::json::parse(made.body)["rater"].get<std::string>();
      for (int guard = 0; guard < 20; ++guard) {
        const auto next = call(http::verb::get, "/api/study/next?rater=" + rater, "");
        if (next.status != 200) return void(++failed);
        const auto j = nlohmann::json::parse(next.body);
        if (j["done"]) return;
        const nlohmann::json vote = {
            {"rater", rater}, {"trial", j["trial"]}, {"answers", {{"physics", "left"}, {"action", "right"}}}};
        if (call(http::verb::post, "/api/study/vote", vote.dump()).status == 200) ++stored;
      }
    });
  for (auto& t : voters) t.join();
  sampling = false;
  sampler.join();
  server.stop();
  EXPECT_EQ(failed, 0);
  EXPECT_EQ(stored, kVoters * 2);  // 2 items x 1 pair each
  EXPECT_LE(peak, before + kVoters + 1) << "no thread per request (" << busy << " answers were 503)";
  VoteStore reader(tmp / "s" / "votes.sqlite");
  EXPECT_EQ(reader.all().size(), static_cast<size_t>(stored * 2));  // two questions a vote
}

}  // namespace
}  // namespace dojo::serve
