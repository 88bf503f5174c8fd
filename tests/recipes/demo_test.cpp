// The demo recipe on a tiny budget: a stage is re-used exactly when nothing that changes its output
// changed (its options, the stages it reads, the seed, the device and precision it computes on), and
// the same seed gives the same report.
#ifdef DOJO_WITH_SIM

#include "recipes/demo.h"

#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <vector>

#include "test_util.h"

namespace fs = std::filesystem;

namespace dojo {
namespace {

const std::vector<std::string> kStages = {"data",         "lam",     "tokenizer",    "probe", "wm_pretrain",
                                          "wm_posttrain", "student", "fast_decoder", "eval",  "eval_student"};

// A whole demo in ~40 s on 2 cores: 2 episodes of 50 frames per dataset, 2 steps per training
// stage, 4 clips per latent cache, 13-frame rollouts at 2 sampler steps, 8 streamed frames, the
// shipped tokenizer.
recipes::DemoOptions tiny_demo(const fs::path& out) {
  recipes::DemoOptions o;
  o.out = out;
  o.episodes = 2;
  o.eval_episodes = 2;  // 2 for the shuffled-action runs
  o.frames = 50;
  o.sampler_steps = 2;
  o.eval_chunks = 1;
  o.workers = 1;
  o.matmul_threads = 1;
  o.lam_steps = o.probe_steps = o.pretrain_steps = o.posttrain_steps = 2;
  o.warmup_steps = o.fast_decoder_steps = 2;
  o.self_forcing_steps = 0;  // the default: the warmed-up student (the CLI demo test runs Self-Forcing)
  o.max_clips = 4;
  o.stream_frames = 8;
  o.tokenizer = fs::path(DOJO_SOURCE_DIR) / "models" / "reference" / "tokenizer";
  return o;
}

// Every stage record's bytes: a stage that runs again rewrites its record (its "seconds" at least
// differ), one that is re-used leaves it alone.
std::map<std::string, std::string> records(const fs::path& out) {
  std::map<std::string, std::string> r;
  for (const auto& name : kStages) r[name] = test::read_file(out / "stages" / (name + ".json"));
  return r;
}

// Runs the demo and returns the stages whose records it rewrote.
std::set<std::string> stages_run(const recipes::DemoOptions& o) {
  const auto before = records(o.out);
  (void)recipes::run_demo(o);
  const auto after = records(o.out);
  std::set<std::string> ran;
  for (const auto& name : kStages) {
    EXPECT_FALSE(after.at(name).empty()) << name << ": no record";
    if (after.at(name) != before.at(name)) ran.insert(name);
  }
  return ran;
}

// Rewrites one field of a stage record's settings, as if the stage had run with it.
void edit_record(const fs::path& out, const std::string& stage, const std::string& key,
                 const std::string& value) {
  const fs::path file = out / "stages" / (stage + ".json");
  auto record = nlohmann::json::parse(test::read_file(file));
  record["settings"][key] = value;
  std::ofstream(file) << record.dump(2) << "\n";
}

// Timings and measured speeds, which differ from run to run whatever the seed.
bool is_timing(const std::string& key) {
  auto ends_with = [&](const std::string& tail) {
    return key.size() >= tail.size() && key.compare(key.size() - tail.size(), tail.size(), tail) == 0;
  };
  return key == "seconds" || key == "finished" || key == "gflops" || ends_with("_seconds") ||
         ends_with("per_second") || key.rfind("step_ms", 0) == 0 || key.rfind("rss", 0) == 0;
}

// Where `a` and `b` differ, timings left out and each run's directory read as OUT: one line each.
void differences(const nlohmann::json& a, const nlohmann::json& b, const fs::path& dir_a,
                 const fs::path& dir_b, const std::string& where, std::vector<std::string>& found) {
  if (a.is_object() && b.is_object()) {
    std::set<std::string> keys;
    for (const auto& [key, value] : a.items()) keys.insert(key);
    for (const auto& [key, value] : b.items()) keys.insert(key);
    for (const auto& key : keys) {
      if (is_timing(key)) continue;
      if (!a.contains(key) || !b.contains(key))
        found.push_back(where + "/" + key + ": in one report only");
      else
        differences(a[key], b[key], dir_a, dir_b, where + "/" + key, found);
    }
    return;
  }
  if (a.is_array() && b.is_array() && a.size() == b.size()) {
    for (size_t i = 0; i < a.size(); ++i)
      differences(a[i], b[i], dir_a, dir_b, where + "/" + std::to_string(i), found);
    return;
  }
  if (a.is_string() && b.is_string()) {
    auto relative = [](std::string s, const std::string& dir) {
      for (size_t at = s.find(dir); at != std::string::npos; at = s.find(dir))
        s.replace(at, dir.size(), "OUT");
      return s;
    };
    if (relative(a.get<std::string>(), dir_a.string()) != relative(b.get<std::string>(), dir_b.string()))
      found.push_back(where + ": " + a.dump() + " vs " + b.dump());
    return;
  }
  if (a != b) found.push_back(where + ": " + a.dump() + " vs " + b.dump());  // numbers exactly
}

// Where two demos' reports (demo.json and every stage record) differ, timings left out.
std::vector<std::string> report_differences(const fs::path& a, const fs::path& b) {
  std::vector<std::string> found;
  auto compare = [&](const std::string& file) {
    differences(nlohmann::json::parse(test::read_file(a / file)),
                nlohmann::json::parse(test::read_file(b / file)), a, b, file, found);
  };
  compare("demo.json");
  for (const auto& name : kStages) compare("stages/" + name + ".json");
  return found;
}

// A tiny demo with seed 0 run once per process (kept until the process ends): the first of the two
// runs compared, and the starting point of the stage-invalidation runs (in a copy).
const fs::path& tiny_demo_seed_0() {
  static const test::TempDir dir;
  static const fs::path out = [] {
    (void)recipes::run_demo(tiny_demo(dir / "demo"));
    return dir / "demo";
  }();
  return out;
}

double elapsed_s(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

TEST(Demo, SameSeedGivesTheSameReport) {
  test::OneThread one;  // the convolution stages take every thread; on a shared machine that spins
  test::TempDir tmp;
  const auto t0 = std::chrono::steady_clock::now();
  const auto first = tiny_demo(tiny_demo_seed_0()), second = tiny_demo(tmp / "second");
  (void)recipes::run_demo(second);
  const auto found = report_differences(first.out, second.out);
  std::string listed;
  for (const auto& line : found) listed += line + "\n";
  EXPECT_TRUE(found.empty()) << found.size() << " differences:\n" << listed;
  // The numbers are there to compare: every split scored, by the teacher and the student.
  const auto demo = nlohmann::json::parse(test::read_file(first.out / "demo.json"));
  ASSERT_EQ(demo["eval"]["result"].size(), 3u);
  EXPECT_TRUE(demo["eval"]["result"][0]["world_model"]["psnr"].is_number()) << demo["eval"].dump();
  ASSERT_EQ(demo["eval_student"]["result"]["splits"].size(), 3u);
  EXPECT_EQ(demo["eval_student"]["result"]["streaming"]["frames"].get<int>(), 8);
  std::printf("same seed, same report: %.1f s\n", elapsed_s(t0));
}

TEST(Demo, ReRunsExactlyTheStagesWhoseInputsChanged) {
  test::OneThread one;
  test::TempDir tmp;
  const auto t0 = std::chrono::steady_clock::now();
  using Set = std::set<std::string>;
  const Set all(kStages.begin(), kStages.end());
  // A finished demo, copied: its records name no path of their own, so the copy re-uses them all.
  fs::copy(tiny_demo_seed_0(), tmp / "demo", fs::copy_options::recursive);
  auto o = tiny_demo(tmp / "demo");
  // Every stage records where it computed: the trainers and the rollouts where asked (here the
  // CPU), DojoSim on the CPU.
  const auto demo = nlohmann::json::parse(test::read_file(o.out / "demo.json"));
  for (const auto& name : kStages) {
    EXPECT_EQ(demo[name]["settings"].value("device", ""), "cpu") << name;
    EXPECT_EQ(demo[name]["settings"].value("precision", ""), "fp32") << name;
    EXPECT_EQ(demo[name]["settings"].value("seed", -1), 0) << name;
  }
  EXPECT_FALSE(fs::exists(o.out / "stages" / "eval.started.json"));

  EXPECT_EQ(stages_run(o), Set{}) << "nothing changed";

  // A stage that runs again with other inputs starts from scratch: its old outputs go first.
  const fs::path sentinel = o.out / "rollouts" / "sentinel";
  std::ofstream(sentinel) << "left by the test\n";
  o.sampler_steps = 1;  // the teacher's rollouts; the student streams its own steps
  EXPECT_EQ(stages_run(o), Set{"eval"}) << "sampler steps";
  EXPECT_FALSE(fs::exists(sentinel));

  o.probe_steps = 3;  // every score reads the probe
  EXPECT_EQ(stages_run(o), (Set{"probe", "eval", "eval_student"})) << "probe steps";

  o.fast_decoder_steps = 3;
  EXPECT_EQ(stages_run(o), (Set{"fast_decoder", "eval_student"})) << "fast decoder steps";

  o.warmup_clean_context_share = 0.25;  // how the student is distilled
  EXPECT_EQ(stages_run(o), (Set{"student", "eval_student"})) << "warm-up clean-context share";

  // A record that says it ran on another device or precision than the stage computes on now is
  // never re-used.
  edit_record(o.out, "fast_decoder", "device", "cuda");
  EXPECT_EQ(stages_run(o), (Set{"fast_decoder", "eval_student"})) << "fast decoder ran on cuda";
  edit_record(o.out, "eval", "precision", "bf16");
  EXPECT_EQ(stages_run(o), Set{"eval"}) << "eval ran in bf16";

  // A new seed: new data (DojoSim refuses to mix two runs in one dataset, so the old one goes
  // first), so every model and score.
  o.seed = 1;
  EXPECT_EQ(stages_run(o), all) << "seed";
  EXPECT_EQ(stages_run(o), Set{}) << "nothing changed";
  // The report comparison of Demo.SameSeedGivesTheSameReport sees another seed's numbers.
  EXPECT_GT(report_differences(tiny_demo_seed_0(), o.out).size(), 10u);

  // Only a run interrupted under the same settings resumes: its outputs stay.
  const auto eval_record = nlohmann::json::parse(test::read_file(o.out / "stages" / "eval.json"));
  std::ofstream(o.out / "stages" / "eval.started.json") << eval_record["settings"].dump(2) << "\n";
  fs::remove(o.out / "stages" / "eval.json");
  std::ofstream(sentinel) << "left by the test\n";
  EXPECT_EQ(stages_run(o), Set{"eval"}) << "eval interrupted";
  EXPECT_TRUE(fs::exists(sentinel));
  EXPECT_FALSE(fs::exists(o.out / "stages" / "eval.started.json"));
  std::printf("%s in %.1f s\n", "the stage-invalidation runs", elapsed_s(t0));
}

}  // namespace
}  // namespace dojo

#endif  // DOJO_WITH_SIM
