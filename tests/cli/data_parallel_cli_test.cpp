// `dojo launch` and data-parallel training on loopback (Gloo), end to end: two processes end with
// the parameters one process reaches on the same global batch split into as many micro-batches;
// distillation, which draws each step whole and splits it by rows, needs no accumulation to match
// a plain run; a rank that dies makes its peer stop with a message, and a rerun resumes.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <thread>

#include "core/checkpoint.h"
#include "core/safetensors.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo {
namespace {

namespace fs = std::filesystem;

// Ports of their own (k < 10) for each test process of this file running beside others (ctest -j),
// below the kernel's ephemeral range (32768 on), where an outgoing connection may hold one.
int port(int k) { return 20000 + static_cast<int>(getpid() % 1200) * 10 + k; }

std::string launch(int k) {
  return "launch --nproc 2 --master-port " + std::to_string(port(k)) + " -- dojo --threads 1 ";
}

// Largest absolute difference between the weights of two checkpoints of one architecture.
double max_difference(const fs::path& a, const fs::path& b) {
  const auto ca = Checkpoint::open(resolve_checkpoint_dir(a)),
             cb = Checkpoint::open(resolve_checkpoint_dir(b));
  EXPECT_EQ(ca.model().keys(), cb.model().keys());
  double worst = 0;
  for (const auto& key : ca.model().keys()) {
    const auto ta = ca.model().tensor(key).to(torch::kFloat64),
               tb = cb.model().tensor(key).to(torch::kFloat64);
    worst = std::max(worst, (ta - tb).abs().max().item<double>());
  }
  return worst;
}

// Whether two checkpoints' trainer states (raw weights, AdamW moments, RNG) hold the same tensors,
// bit for bit, and how many AdamW moment tensors they hold.
int64_t equal_trainer_states(const fs::path& a, const fs::path& b) {
  const auto ca = Checkpoint::open(resolve_checkpoint_dir(a)),
             cb = Checkpoint::open(resolve_checkpoint_dir(b));
  EXPECT_EQ(ca.trainer_tensors().keys(), cb.trainer_tensors().keys());
  int64_t moments = 0;
  for (const auto& key : ca.trainer_tensors().keys()) {
    EXPECT_TRUE(torch::equal(ca.trainer_tensors().tensor(key), cb.trainer_tensors().tensor(key))) << key;
    moments += key.find(".exp_avg") != std::string::npos;
  }
  return moments;
}

// Two processes and one add the same gradients in another order; AdamW turns the last bits of a
// near-zero gradient into up to a full step, so the runs agree to a tenth of the learning rate
// (1e-3 in these runs), not to the last bit.
constexpr double kTolerance = 1e-4;

// How far each checkpoint moved from `start`: the equivalence must not hold only because no
// parameter moved at all.
double moved(const fs::path& start, const fs::path& end) { return max_difference(start, end); }

// Three synthetic robot episodes of 26 frames and a held-out one: enough for a few steps of
// every trainer.
void write_tiny_robot_set(const fs::path& dir) {
  test::SyntheticOptions g;
  g.episodes = 3;
  g.frames = 26;
  g.val_episodes = 1;
  test::write_synthetic_dataset(dir, g);
}

TEST(DataParallelCli, TwoProcessesTrainAsOneProcessWithTwoMicroBatches) {
  test::TempDir tmp;
  write_tiny_robot_set(tmp / "robot");
  const auto data = " --data " + (tmp / "robot").string();
  const auto out = [&](const std::string& name) { return " --out " + (tmp / name).string(); };

  // Tokenizer (its own clip loader, shared between the ranks by stream index).
  const std::string tok_args =
      "tokenizer train --steps 2 --batch 2 --frames 5 --size 32 --dim 8 --workers 1 --split all --lr 1e-3" +
      data;
  auto r = test::run_dojo("--threads 1 " + tok_args + " --accumulate 2" + out("tok1"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo(launch(0) + tok_args + out("tok2"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_LT(max_difference(tmp / "tok1", tmp / "tok2"), kTolerance);
  const auto tok = " --tokenizer " + (tmp / "tok1").string();

  // World model: the first step alone, then two more resumed, against the same three steps on one
  // process. Rank 0 caches the latents; the other reads them.
  const std::string wm_args =
      "wm train --stage scratch --batch 4 --hop 4 --save-every 1 --lr 1e-3 --warmup 0" + data + tok;
  r = test::run_dojo("--threads 1 " + wm_args + " --steps 3 --accumulate 2" + out("wm1"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo(launch(1) + wm_args + " --steps 1" + out("wm2"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo(launch(2) + wm_args + " --steps 3" + out("wm2"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("resumed from"), std::string::npos) << r.output;
  EXPECT_LT(max_difference(tmp / "wm1" / "checkpoint", tmp / "wm2" / "checkpoint"), kTolerance);
  r = test::run_dojo("--threads 1 " + wm_args + " --steps 3" + out("wm_plain"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_GT(moved(tmp / "wm_plain" / "checkpoint", tmp / "wm1" / "checkpoint"), 1e-4)
      << "two micro-batches of 2 are other draws than one batch of 4: the comparison above is not trivial";
  const auto summary = nlohmann::json::parse(test::read_file(tmp / "wm2" / "train_summary.json"));
  EXPECT_EQ(summary.at("processes"), 2);
  // The all-reduce ran during the backward pass (buckets started before it returned), and gave the
  // bits of the all-reduce after it (DOJO_DIST_OVERLAP=0).
  EXPECT_GT(summary.at("allreduce_buckets").get<int64_t>(), 1);
  EXPECT_GT(summary.at("allreduce_buckets_started_in_backward").get<int64_t>(), 0);
  const std::string after_backward = "DOJO_DIST_OVERLAP=0 " + std::string(DOJO_EXE) + " ";
  r = test::run_command(after_backward + launch(8) + wm_args + " --steps 1" + out("wm4"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_command(after_backward + launch(9) + wm_args + " --steps 3" + out("wm4"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(max_difference(tmp / "wm2" / "checkpoint", tmp / "wm4" / "checkpoint"), 0.0);
  EXPECT_EQ(
      nlohmann::json::parse(test::read_file(tmp / "wm4" / "train_summary.json")).at("allreduce_buckets"), 0);
  // ZeRO-1: each process keeps half the moments; the weights, the EMA and the gathered moments of
  // the checkpoint are those of plain data parallelism bit for bit, across a resume too.
  r = test::run_dojo(launch(6) + wm_args + " --zero1 --steps 1" + out("wm3"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo(launch(7) + wm_args + " --zero1 --steps 3" + out("wm3"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(max_difference(tmp / "wm2" / "checkpoint", tmp / "wm3" / "checkpoint"), 0.0);
  EXPECT_GT(equal_trainer_states(tmp / "wm2" / "checkpoint", tmp / "wm3" / "checkpoint"), 0);
  const auto sharded = nlohmann::json::parse(test::read_file(tmp / "wm3" / "train_summary.json"));
  EXPECT_EQ(sharded.at("zero1"), true);
  EXPECT_NEAR(sharded.at("optimizer_moment_mib_per_process").get<double>(),
              summary.at("optimizer_moment_mib_per_process").get<double>() / 2, 1e-3);
  r = test::run_dojo("--threads 1 wm train --stage scratch --hop 4 --steps 1 --batch 3 --accumulate 2" +
                     data + tok + out("bad"));
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("a batch of 3 does not split into 2 equal micro-batches"), std::string::npos)
      << r.output;

  // The plain AdamW loop (fast decoder; the probe, detector and behaviour cloning share it).
  const std::string fd_args =
      "tokenizer fast-decoder --split all --max-clips 4 --steps 2 --batch 2" + data + tok;
  r = test::run_dojo("--threads 1 " + fd_args + " --accumulate 2" + out("fd1"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo(launch(3) + fd_args + out("fd2"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_LT(max_difference(tmp / "fd1" / "checkpoint", tmp / "fd2" / "checkpoint"), kTolerance);

  // Distillation warm-up from the tiny teacher: a plain run and two processes, no accumulation.
  const std::string distill_args =
      "distill --teacher " + (tmp / "wm1" / "checkpoint").string() + tok + data +
      " --split all --max-clips 4 --teacher-steps 4 --steps 2 --batch 2 --lr 1e-3";
  r = test::run_dojo("--threads 1 " + distill_args + out("d1"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo(launch(4) + distill_args + out("d2"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_LT(max_difference(tmp / "d1" / "checkpoint", tmp / "d2" / "checkpoint"), kTolerance);
  // Self-Forcing from that student: a generator update, then a critic update, each split by rows.
  const std::string sf_args =
      "distill --stage self-forcing --init " + (tmp / "d1" / "checkpoint").string() + " --teacher " +
      (tmp / "wm1" / "checkpoint").string() + tok + data +
      " --split all --max-clips 2 --min-frames 4 --max-frames 5 --critic-steps 1 --steps 2 "
      "--batch 2 --generator-lr 1e-3 --critic-lr 1e-3";
  r = test::run_dojo("--threads 1 " + sf_args + out("sf1"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo(launch(9) + sf_args + out("sf2"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_LT(max_difference(tmp / "sf1" / "checkpoint", tmp / "sf2" / "checkpoint"), kTolerance);
  EXPECT_LT(max_difference(tmp / "sf1" / "critic", tmp / "sf2" / "critic"), kTolerance);
  // ZeRO-1 for both stages: the bits of plain data parallelism, half the moments a process.
  r = test::run_dojo(launch(8) + distill_args + " --zero1" + out("d3"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(max_difference(tmp / "d2" / "checkpoint", tmp / "d3" / "checkpoint"), 0.0);
  EXPECT_GT(equal_trainer_states(tmp / "d2" / "checkpoint", tmp / "d3" / "checkpoint"), 0);
  r = test::run_dojo(launch(7) + sf_args + " --zero1" + out("sf3"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(max_difference(tmp / "sf2" / "checkpoint", tmp / "sf3" / "checkpoint"), 0.0);
  EXPECT_EQ(max_difference(tmp / "sf2" / "critic", tmp / "sf3" / "critic"), 0.0);
  EXPECT_GT(equal_trainer_states(tmp / "sf2" / "checkpoint", tmp / "sf3" / "checkpoint"), 0);
  EXPECT_GT(equal_trainer_states(tmp / "sf2" / "critic", tmp / "sf3" / "critic"), 0);
  for (const char* run : {"d", "sf"}) {
    const auto plain =
        nlohmann::json::parse(test::read_file(tmp / (std::string(run) + "2") / "distill_summary.json"));
    const auto sharded =
        nlohmann::json::parse(test::read_file(tmp / (std::string(run) + "3") / "distill_summary.json"));
    EXPECT_EQ(sharded.at("zero1"), true) << run;
    EXPECT_NEAR(sharded.at("optimizer_moment_mib_per_process").get<double>(),
                plain.at("optimizer_moment_mib_per_process").get<double>() / 2, 1e-3)
        << run;
  }

  // LAM (frame pairs from its clip loader).
  const std::string lam_args = "lam train --model tiny --steps 2 --batch 2 --lr 1e-3" + data;
  r = test::run_dojo("--threads 1 " + lam_args + " --accumulate 2" + out("lam1"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo(launch(5) + lam_args + out("lam2"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_LT(max_difference(tmp / "lam1" / "checkpoint", tmp / "lam2" / "checkpoint"), kTolerance);
}

// The trainers on run_adamw_loop that the test above does not run (it runs the fast decoder's and
// the LAM's): the keypoint probe, behaviour cloning and the success detector, each a plain run, one
// process with two micro-batches and two processes.
TEST(DataParallelCli, ProbeBehaviourCloningAndDetectorTrainAsOneProcessWithTwoMicroBatches) {
  test::TempDir tmp;
  write_tiny_robot_set(tmp / "robot");
  const auto out = [&](const std::string& name) { return " --out " + (tmp / name).string(); };
  // Each trainer: one process with --accumulate 2 and two processes end alike, and far from a
  // plain run of one batch (other draws): the agreement is not that of weights that did not move.
  const auto expect_equivalent = [&](const std::string& name, const std::string& args, int port_index) {
    auto r = test::run_dojo("--threads 1 " + args + " --accumulate 2" + out(name + "1"));
    ASSERT_EQ(r.exit_code, 0) << name << ": " << r.output;
    r = test::run_dojo(launch(port_index) + args + out(name + "2"));
    ASSERT_EQ(r.exit_code, 0) << name << ": " << r.output;
    r = test::run_dojo("--threads 1 " + args + out(name + "_plain"));
    ASSERT_EQ(r.exit_code, 0) << name << ": " << r.output;
    const auto checkpoint = [&](const std::string& run) { return tmp / run / "checkpoint"; };
    EXPECT_LT(max_difference(checkpoint(name + "1"), checkpoint(name + "2")), kTolerance) << name;
    EXPECT_GT(moved(checkpoint(name + "_plain"), checkpoint(name + "1")), 1e-4) << name;
  };
  expect_equivalent("probe",
                    "probe train --data " + (tmp / "robot").string() +
                        " --split all --size 32 --width 8 --steps 3 --batch 4 --lr 1e-3",
                    0);
#ifdef DOJO_WITH_SIM
  expect_equivalent("bc", "policy train --episodes 4 --frames 24 --steps 4 --batch 8", 1);
  std::ofstream(tmp / "set.json")
      << R"({"policies": [{"name": "expert"}, {"name": "idle", "behavior": "idle"}]})";
  expect_equivalent("detector",
                    "policy detector --scenes 2 --steps 4 --policies " + (tmp / "set.json").string(), 2);
#endif
}

TEST(DataParallelCli, ALauncherStopsEveryRankWhenOneFailsAndReportsItsStatus) {
  const auto t0 = std::chrono::steady_clock::now();
  auto r = test::run_dojo("launch --nproc 3 --grace 2 --master-port " + std::to_string(port(6)) +
                          " -- sh -c 'if [ \"$RANK\" = 1 ]; then exit 7; fi; sleep 60'");
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  EXPECT_EQ(r.exit_code, 7) << r.output;
  EXPECT_LT(seconds, 20) << "the sleeping ranks were stopped, not waited for";
  EXPECT_NE(r.output.find("rank 1 exited with status 7; stopping the other 2"), std::string::npos)
      << r.output;
  // Every rank sees torchrun's variables.
  r = test::run_dojo(
      "launch --nproc 2 --master-port " + std::to_string(port(7)) +
      " -- sh -c 'echo \"rank=$RANK/$WORLD_SIZE local=$LOCAL_RANK at $MASTER_ADDR:$MASTER_PORT\"'");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  for (const auto* rank : {"rank=0/2 local=0", "rank=1/2 local=1"})
    EXPECT_NE(r.output.find(std::string(rank) + " at 127.0.0.1:" + std::to_string(port(7))),
              std::string::npos)
        << r.output;
  r = test::run_dojo("launch --nproc 2 -- /nonexistent/program");
  EXPECT_EQ(r.exit_code, 127) << r.output;
}

TEST(DataParallelCli, ADeadRankStopsItsPeerWithAMessageAndTheRunResumes) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 2;
  g.frames = 26;
  g.val_episodes = 0;
  test::write_synthetic_dataset(tmp / "robot", g);
  const auto data = " --data " + (tmp / "robot").string();
  auto r = test::run_dojo(
      "--threads 1 tokenizer train --steps 1 --batch 1 --frames 5 --size 32 --dim 8 --workers 1 "
      "--split all --out " +
      (tmp / "tok").string() + data);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto run = tmp / "run";
  const std::string args = "wm train --stage scratch --batch 2 --hop 4 --save-every 1 --split all" + data +
                           " --tokenizer " + (tmp / "tok").string() + " --out " + run.string();
  // Both ranks started by hand, as on two machines; rank 1 is killed once a checkpoint exists.
  const int master_port = port(8);  // here: a forked child has another pid
  const auto rank = [&](int r, const std::string& log) {
    return "env RANK=" + std::to_string(r) +
           " WORLD_SIZE=2 MASTER_ADDR=127.0.0.1 MASTER_PORT=" + std::to_string(master_port) +
           " DOJO_DIST_TIMEOUT=30 " + std::string(DOJO_EXE) + " --threads 1 " + args + " --steps 100000 > " +
           log + " 2>&1";
  };
  const pid_t rank0 = fork();
  if (rank0 == 0) {
    execl("/bin/sh", "sh", "-c", rank(0, (tmp / "rank0.log").string()).c_str(), static_cast<char*>(nullptr));
    _exit(127);
  }
  const pid_t rank1 = fork();
  if (rank1 == 0) {
    execl("/bin/sh", "sh", "-c", ("exec " + rank(1, (tmp / "rank1.log").string())).c_str(),
          static_cast<char*>(nullptr));
    _exit(127);
  }
  // Whatever fails below, no rank outlives the test.
  struct Reaper {
    pid_t pids[2];
    ~Reaper() {
      for (const pid_t p : pids)
        if (waitpid(p, nullptr, WNOHANG) == 0) kill(p, SIGKILL), waitpid(p, nullptr, 0);  // still running
    }
  } reaper{{rank0, rank1}};
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  while (!checkpoint_exists(run / "checkpoint") && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_TRUE(checkpoint_exists(run / "checkpoint")) << test::read_file(tmp / "rank0.log") << "\nrank 1:\n"
                                                     << test::read_file(tmp / "rank1.log");
  kill(rank1, SIGKILL);
  const auto killed = std::chrono::steady_clock::now();
  int status = 0;
  waitpid(rank1, &status, 0);
  waitpid(rank0, &status, 0);
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - killed).count();
  EXPECT_LT(seconds, 40) << "rank 0 stops within its timeout";
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 1);
  const auto log = test::read_file(tmp / "rank0.log");
  EXPECT_NE(log.find("data parallel (rank 0 of 2)"), std::string::npos) << log;
  EXPECT_NE(log.find("rerun the same command to resume"), std::string::npos) << log;

  const int64_t saved = Checkpoint::open(resolve_checkpoint_dir(run / "checkpoint")).step();
  r = test::run_dojo(launch(1) + args + " --steps " + std::to_string(saved + 2));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(
      r.output.find("resumed from " + (run / "checkpoint").string() + " at step " + std::to_string(saved)),
      std::string::npos)
      << r.output;
  EXPECT_EQ(Checkpoint::open(resolve_checkpoint_dir(run / "checkpoint")).step(), saved + 2);
}

}  // namespace
}  // namespace dojo
