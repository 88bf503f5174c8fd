// Fuzzing what clients send: thousands of mutated WebSocket messages (byte flips, cuts, splices,
// wrong types, huge and non-finite numbers, deep nesting, binary junk) into a live step-mode
// session on the reference model, mutated POST /v1/rollout bodies and study votes. Nothing may
// throw or crash; every message that is not a JSON object is answered with an error; afterwards
// the same session still starts and steps. Deterministic: a fixed seed drives the mutations.
#include <gtest/gtest.h>

#include <condition_variable>
#include <mutex>
#include <random>

#include "io/video.h"
#include "serve/model_host.h"
#include "serve/rollout_api.h"
#include "serve/session.h"
#include "serve/study_api.h"
#include "serve/study_create.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo::serve {
namespace {

// Mutations of a seed message, in the spirit of a byte-level fuzzer plus JSON-aware ones.
class Mutator {
 public:
  explicit Mutator(uint64_t seed) : rng_(seed) {}
  std::string mutate(std::string s) {
    const int rounds = 1 + pick(3);
    for (int r = 0; r < rounds; ++r) {
      switch (pick(9)) {
        case 0:  // flip a byte
          if (!s.empty()) s[pick(s.size())] ^= static_cast<char>(1 << pick(8));
          break;
        case 1:  // insert a random byte
          s.insert(s.begin() + pick(s.size() + 1), static_cast<char>(pick(256)));
          break;
        case 2:  // cut a range
          if (!s.empty()) {
            const size_t at = pick(s.size());
            s.erase(at, pick(s.size() - at + 1));
          }
          break;
        case 3:  // duplicate a range
          if (!s.empty()) {
            const size_t at = pick(s.size());
            s.insert(at, s.substr(at, pick(16)));
          }
          break;
        case 4:  // a number becomes something else
        case 5: {
          static const char* kValues[] = {"1e308", "-1e308",      "NaN", "-1",     "\"x\"",
                                          "null",  "[]",          "{}",  "1e-320", "18446744073709551616",
                                          "true",  "[[1,2],[3]]", "0.5"};
          const size_t at = s.find_first_of("0123456789", pick(s.size() + 1));
          if (at != std::string::npos) {
            const size_t end = s.find_first_not_of("0123456789.e-", at);
            s.replace(at, (end == std::string::npos ? s.size() : end) - at,
                      kValues[pick(std::size(kValues))]);
          }
          break;
        }
        case 6:  // a field name changes
        {
          static const char* kNames[] = {"type", "actions", "velocity", "value", "mode",
                                         "seed", "on",      "t",        ""};
          const size_t at = s.find('"', pick(s.size() + 1));
          if (at != std::string::npos) {
            const size_t end = s.find('"', at + 1);
            if (end != std::string::npos) s.replace(at + 1, end - at - 1, kNames[pick(std::size(kNames))]);
          }
          break;
        }
        case 7:  // splice another seed in
          s.insert(pick(s.size() + 1), "{\"type\":\"step\",\"actions\":[[");
          break;
        default:  // truncate
          s.resize(pick(s.size() + 1));
      }
    }
    return s;
  }
  size_t pick(size_t n) { return n ? std::uniform_int_distribution<size_t>(0, n - 1)(rng_) : 0; }

 private:
  std::mt19937_64 rng_;
};

std::vector<std::string> seed_messages() {
  return {
      R"({"type":"start","mode":"step","seed":0})",
      R"({"type":"control","velocity":[0.1,0,0,0,0,0],"t":12.5})",
      R"({"type":"command","value":[1.0,0.5,1.8,0.8,0,0.5],"t":3})",
      R"({"type":"step","actions":[[1.0,0.5,1.8,0.8,0,0.5],[1.0,0.5,1.8,0.8,0,0.5],[1.0,0.5,1.8,0.8,0,0.5],[1.0,0.5,1.8,0.8,0,0.5]]})",
      R"({"type":"reset"})",
      R"({"type":"record","on":false})",
      R"({"type":"step","actions":[[0.25]]})"};
}

TEST(ServeFuzz, MutatedMessagesNeverBreakASession) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 1;
  g.frames = 16;
  g.size = 64;
  g.val_episodes = 1;
  test::write_synthetic_dataset(tmp / "robot", g);
  const auto reference = std::filesystem::path(DOJO_SOURCE_DIR) / "models" / "reference";
  ModelHost::Options h;
  ModelSpec student;
  student.name = "student";
  student.checkpoint = reference / "wm_posttrain";
  student.tokenizer = reference / "tokenizer";
  h.models = {student};
  h.data = tmp / "robot";
  ModelHost host(h);
  host.load();
  ServerMetrics metrics;

  std::mutex mutex;
  std::condition_variable arrived;
  std::vector<Outgoing> out;
  SessionOptions o;
  o.recordings = tmp / "recordings";
  Session session(host, o, metrics, [&](Outgoing m) {
    std::lock_guard<std::mutex> lock(mutex);
    out.push_back(std::move(m));
    arrived.notify_all();
  });
  const auto wait_for = [&](const std::string& type) {
    std::unique_lock<std::mutex> lock(mutex);
    return arrived.wait_for(lock, std::chrono::seconds(60), [&] {
      for (const auto& m : out)
        if (!m.binary && m.data.find("\"type\":\"" + type + "\"") != std::string::npos) return true;
      return false;
    });
  };
  session.on_text(R"({"type":"start","mode":"step","seed":0})");
  ASSERT_TRUE(wait_for("ready"));
  const auto json_errors = [&] {  // errors saying a message was not a JSON object
    std::lock_guard<std::mutex> lock(mutex);
    int n = 0;
    for (const auto& m : out)
      n += !m.binary && (m.data.find("not valid JSON") != std::string::npos ||
                         m.data.find("must be a JSON object") != std::string::npos);
    return n;
  };

  Mutator mutator(20261124);
  const auto seeds = seed_messages();
  int not_objects = 0;
  for (int i = 0; i < 3000; ++i) {
    auto message = mutator.mutate(seeds[mutator.pick(seeds.size())]);
    if (message.find("\"start\"") != std::string::npos || message.find("\"record\"") != std::string::npos)
      continue;  // restarts and recordings are exercised elsewhere; here they would only cost time
    const auto parsed = nlohmann::json::parse(message, nullptr, false);
    const bool not_object = parsed.is_discarded() || !parsed.is_object();
    not_objects += not_object;
    const auto before = json_errors();
    EXPECT_NO_THROW(session.on_text(message));
    // A message that is not a JSON object is answered at once, on the caller's thread.
    if (not_object) {
      EXPECT_EQ(json_errors(), before + 1) << message;
    }
    if (i % 50 == 0) {
      EXPECT_NO_THROW(session.on_binary(message));
    }
  }
  // Deep nesting and a large junk message.
  const std::string deep = std::string(100000, '[') + std::string(100000, ']');
  auto before = json_errors();
  session.on_text(deep);
  EXPECT_EQ(json_errors(), before + 1);
  before = json_errors();
  session.on_text(std::string(1 << 20, '{'));
  EXPECT_EQ(json_errors(), before + 1);
  not_objects += 2;

  // Every message that was not a JSON object got an error back (others may be valid or not).
  {
    std::lock_guard<std::mutex> lock(mutex);
    int errors = 0;
    for (const auto& m : out) errors += !m.binary && m.data.find("\"type\":\"error\"") != std::string::npos;
    EXPECT_GE(errors, not_objects);
    out.clear();
  }
  // The session still works: a fresh start and a valid step.
  session.on_text(R"({"type":"start","mode":"step","seed":1})");
  ASSERT_TRUE(wait_for("ready"));
  session.on_text(seeds[3]);
  ASSERT_TRUE(wait_for("step_done"));
  session.close();

  // Mutated rollout bodies: a reply for each, 200 or 4xx, never an exception.
  Mutator bodies(7);
  const std::string rollout =
      R"({"model":"student","format":"jpeg","seed":0,"actions":[[1.0,0.5,1.8,0.8,0,0.5],[1.0,0.5,1.8,0.8,0,0.5],[1.0,0.5,1.8,0.8,0,0.5],[1.0,0.5,1.8,0.8,0,0.5]]})";
  for (int i = 0; i < 300; ++i) {
    const auto reply =
        run_rollout_request(host, bodies.mutate(rollout), metrics, RolloutLimits{1200, 300, 80});
    EXPECT_TRUE(reply.status == 200 || reply.status == 400) << reply.status << " " << reply.body;
  }
}

TEST(ServeFuzz, MutatedStudyVotesAreRefusedCleanly) {
  test::TempDir tmp;
  for (const auto* name : {"truth", "a", "b"}) {
    std::filesystem::create_directories(tmp / "clips" / "ep");
    io::write_video((tmp / "clips" / "ep" / (std::string(name) + ".mp4")).string(),
                    torch::zeros({2, 16, 16, 3}, torch::kUInt8));
  }
  create_study_from_videos(tmp / "s", tmp / "clips", {"a", "b"}, "");
  StudyApi api(tmp / "s");
  const auto rater = nlohmann::json::parse(api.handle("POST", "/api/study/raters", "", "", "").body)["rater"];
  const auto trial = nlohmann::json::parse(api.handle("GET", "/api/study/next", rater, "", "").body)["trial"];
  const std::string vote =
      nlohmann::json{
          {"rater", rater}, {"trial", trial}, {"answers", {{"physics", "left"}, {"action", "tie"}}}}
          .dump();
  Mutator mutator(11);
  int stored = 0;
  for (int i = 0; i < 2000; ++i) {
    const auto reply = api.handle("POST", "/api/study/vote", "", mutator.mutate(vote), "");
    EXPECT_TRUE(reply.status == 200 || reply.status == 400 || reply.status == 409)
        << reply.status << reply.body;
    stored += reply.status == 200;
  }
  EXPECT_LE(stored, 1);  // one trial: at most one vote can land
  EXPECT_EQ(api.votes().all().size(), static_cast<size_t>(2 * stored));
}

}  // namespace
}  // namespace dojo::serve
