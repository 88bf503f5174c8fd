// The load test: concurrent sessions against a server on loopback for a bounded time, in step and
// live mode, then more sessions than the cap. Nothing crashes, every session gets frames, no error
// reaches a well-behaved client, the server still answers, refused sessions are counted. Numbers
// (frames/s, latency, memory) are benchmarks (`dojo serve-load`, docs/benchmarks.md), not asserted.
#include "serve/load.h"

#include <gtest/gtest.h>

#include <chrono>
#include <filesystem>
#include <thread>

#include "io/video.h"
#include "serve/model_host.h"
#include "serve/server.h"
#include "serve/study.h"
#include "serve/study_create.h"
#include "sessions_drained.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo::serve {
namespace {

TEST(ServeLoad, ConcurrentSessionsStepAndLiveThenOverTheCap) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 2;
  g.frames = 16;
  g.size = 64;
  g.val_episodes = 2;
  test::write_synthetic_dataset(tmp / "robot", g);
  const auto reference = std::filesystem::path(DOJO_SOURCE_DIR) / "models" / "reference";
  ModelHost::Options h;
  ModelSpec student;
  student.name = "student";
  student.checkpoint = reference / "wm_posttrain";
  student.tokenizer = reference / "tokenizer";
  h.models = {student};
  h.data = tmp / "robot";
  auto host = std::make_shared<ModelHost>(h);
  host->load();
  ServeOptions o;
  o.port = 0;
  o.max_sessions = 4;
  o.fps = 40;
  o.recordings = tmp / "recordings";
  Server server(o, host);
  LoadOptions load;
  load.port = server.start();
  load.seconds = 3;
  load.min_frames = 8;  // two steps: how many fit in 3 s depends on the machine, not the server

  load.sessions = 4;
  load.mode = "step";
  const auto step = run_load(load);
  EXPECT_EQ(step.failed_sessions, 0) << step.to_json().dump();
  EXPECT_EQ(step.errors, 0);
  ASSERT_EQ(step.frames.size(), 4u);
  for (const auto f : step.frames) EXPECT_GE(f, 8) << step.to_json().dump();
  EXPECT_GT(step.latency_ms_p50, 0);
  EXPECT_GT(step.server_rss_mib_after, 0);

  // Between phases every session of the last one must be gone.
  const auto drained = [&] { return test::sessions_drained(server); };
  ASSERT_TRUE(drained());
  load.sessions = 2;
  load.mode = "live";
  const auto live = run_load(load);
  EXPECT_EQ(live.failed_sessions, 0) << live.to_json().dump();
  EXPECT_EQ(live.errors, 0);
  for (const auto f : live.frames) EXPECT_GE(f, 8) << live.to_json().dump();

  ASSERT_TRUE(drained());
  load.sessions = 6;  // two over the cap: refused with a 503, the others run
  load.seconds = 1;
  load.min_frames = 4;
  load.mode = "step";
  const auto over = run_load(load);
  EXPECT_EQ(over.refused_sessions, 2) << over.to_json().dump();
  EXPECT_EQ(over.failed_sessions, 0) << over.to_json().dump();
  EXPECT_EQ(over.frames.size(), 4u);
  EXPECT_NE(server.metrics().prometheus_text().find("dojo_sessions_refused_total 2\n"), std::string::npos);
  EXPECT_TRUE(drained());
  server.stop();
}

// Study voters against a study server (no model) with a small pool: every vote the server
// acknowledged is in the database, busy answers are retried, and a server stopped under the
// voters ends them with what they had, reported rather than thrown.
TEST(ServeLoad, StudyVotersAreAcknowledgedStoredAndCountedWhenTheServerGoes) {
  test::TempDir tmp;
  const auto clips = tmp / "clips" / "ep-0";
  std::filesystem::create_directories(clips);
  for (const auto* name : {"truth", "a", "b"})
    io::write_video((clips / (std::string(name) + ".mp4")).string(),
                    torch::full({3, 16, 16, 3}, 90, torch::kUInt8));
  create_study_from_videos(tmp / "s", tmp / "clips", {"a", "b"}, "");
  auto host = std::make_shared<ModelHost>(ModelHost::Options{});
  host->load();
  ServeOptions o;
  o.port = 0;
  o.study = tmp / "s";
  o.study_threads = 2;
  o.max_study_requests = 3;
  Server server(o, host);
  LoadOptions load;
  load.port = server.start();
  load.mode = "study";
  load.sessions = 8;
  load.seconds = 1.5;
  const auto run = run_load(load);
  EXPECT_EQ(run.failed_sessions, 0) << run.to_json().dump();
  EXPECT_GT(run.votes_acknowledged, 8) << run.to_json().dump();
  EXPECT_EQ(run.answers_acknowledged, 2 * run.votes_acknowledged);  // two questions a trial
  EXPECT_GT(run.latency_ms_p99, 0);
  EXPECT_TRUE(run.server_alive_after);
  EXPECT_EQ(static_cast<int64_t>(VoteStore(tmp / "s" / "votes.sqlite").all().size()),
            run.answers_acknowledged);

  load.seconds = 30;
  // Stop once the voters have stored a trial of this run (so some vote was acknowledged before
  // the cut), not after a fixed delay a slow disk could outlast.
  const auto stored_before = static_cast<int64_t>(VoteStore(tmp / "s" / "votes.sqlite").all().size());
  std::thread stopper([&] {
    const auto waiting_since = std::chrono::steady_clock::now();
    while (static_cast<int64_t>(VoteStore(tmp / "s" / "votes.sqlite").all().size()) < stored_before + 4 &&
           std::chrono::steady_clock::now() - waiting_since < std::chrono::seconds(10))
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    server.stop();
  });
  const auto cut_start = std::chrono::steady_clock::now();
  const auto cut = run_load(load);
  stopper.join();
  // The voters learn at once that the server went (connections closed, new work refused), not
  // from the load client's watchdog a minute past the 30 s run.
  EXPECT_LT(std::chrono::duration<double>(std::chrono::steady_clock::now() - cut_start).count(), 15);
  EXPECT_FALSE(cut.server_alive_after);
  EXPECT_EQ(cut.failed_sessions, 8) << cut.to_json().dump();
  EXPECT_GT(cut.votes_acknowledged, 0);
  // A vote stored as the server went may have lost its answer: never fewer rows than acknowledged.
  EXPECT_GE(static_cast<int64_t>(VoteStore(tmp / "s" / "votes.sqlite").all().size()),
            run.answers_acknowledged + cut.answers_acknowledged);
}

}  // namespace
}  // namespace dojo::serve
