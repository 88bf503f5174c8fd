// The load test: concurrent sessions against a server on loopback for a bounded time, in step and
// live mode, then more sessions than the cap. Nothing crashes, every session gets frames, no error
// reaches a well-behaved client, the server still answers, refused sessions are counted. Numbers
// (frames/s, latency, memory) are benchmarks (`dojo serve-load`, docs/benchmarks.md), not asserted.
#include "serve/load.h"

#include <gtest/gtest.h>

#include <thread>

#include "serve/model_host.h"
#include "serve/server.h"
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
  EXPECT_EQ(over.failed_sessions, 2) << over.to_json().dump();
  EXPECT_EQ(over.frames.size(), 4u);
  for (const auto& failure : over.failures) EXPECT_NE(failure.find("declined"), std::string::npos) << failure;
  EXPECT_NE(server.metrics().prometheus_text().find("dojo_sessions_refused_total 2\n"), std::string::npos);
  EXPECT_TRUE(drained());
  server.stop();
}

}  // namespace
}  // namespace dojo::serve
