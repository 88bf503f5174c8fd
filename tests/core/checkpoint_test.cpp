// Checkpoint directories: round trip, overwrite, errors, RNG state, and crash safety: a save
// SIGKILLed at every crash point, and at random moments, leaves a loadable complete checkpoint.
#include "core/checkpoint.h"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <fstream>
#include <random>
#include <thread>

#include "core/atomic_file.h"
#include "core/error.h"
#include "test_util.h"

namespace dojo {
namespace {

namespace fs = std::filesystem;

// A checkpoint whose every number encodes its step, so a mix of two saves is detectable.
CheckpointData make_checkpoint(int64_t step, int64_t model_elements = 1000) {
  CheckpointData data;
  data.config = {{"model", "tiny"}, {"dim", 16}, {"saved_at_step", step}};
  data.model = {{"net.w", torch::full({model_elements}, static_cast<float>(step))},
                {"net.b", torch::full({16}, static_cast<double>(step), torch::kFloat64).to(torch::kBFloat16)},
                {"net.count", torch::full({}, step, torch::kInt64)}};
  TrainerState trainer;
  trainer.step = step;
  trainer.extra = {{"epoch", step / 10}, {"data_cursor", {{"shard", 3}, {"offset", step * 7}}}};
  trainer.tensors = {{"optim.net.w.exp_avg", torch::full({model_elements}, static_cast<float>(step))},
                     {"ema.net.w", torch::full({model_elements}, static_cast<float>(step))}};
  data.trainer = std::move(trainer);
  return data;
}

// Opens DIR and checks it is one complete checkpoint; returns its step.
int64_t open_consistent(const fs::path& dir) {
  const Checkpoint ckpt = Checkpoint::open(dir);
  const int64_t step = ckpt.step();
  EXPECT_EQ(ckpt.config()["saved_at_step"], step);
  EXPECT_EQ(nlohmann::json::parse(ckpt.model().metadata().at("config"))["saved_at_step"], step);
  EXPECT_EQ(ckpt.trainer_extra()["data_cursor"]["offset"], step * 7);
  // (BF16 rounds large steps the same way the writer did.)
  for (const auto* file : {&ckpt.model(), &ckpt.trainer_tensors()})
    for (const auto& [name, tensor] : file->tensors())
      EXPECT_TRUE(torch::equal(tensor, torch::full_like(tensor, static_cast<double>(step))))
          << name << " at step " << step;
  return step;
}

std::vector<std::string> entries(const fs::path& dir) {
  std::vector<std::string> out;
  for (const auto& entry : fs::directory_iterator(dir)) out.push_back(entry.path().filename().string());
  std::sort(out.begin(), out.end());
  return out;
}

TEST(Checkpoint, SaveAndOpenRoundTrip) {
  test::TempDir root;
  const auto dir = root / "ckpt";
  const CheckpointData data = make_checkpoint(12);
  save_checkpoint(dir, data);
  EXPECT_EQ(entries(root.path()), std::vector<std::string>{"ckpt"});
  EXPECT_EQ(entries(dir), (std::vector<std::string>{"config.json", "model.safetensors", "trainer_state.json",
                                                    "trainer_state.safetensors"}));

  const Checkpoint ckpt = Checkpoint::open(dir);
  EXPECT_EQ(ckpt.config(), data.config);
  EXPECT_EQ(ckpt.model().keys(), (std::vector<std::string>{"net.w", "net.b", "net.count"}));
  EXPECT_EQ(ckpt.model().info("net.b").dtype, "BF16");
  EXPECT_EQ(ckpt.step(), 12);
  EXPECT_EQ(ckpt.trainer_extra(), data.trainer->extra);
  EXPECT_EQ(open_consistent(dir), 12);
  EXPECT_EQ(nlohmann::json::parse(test::read_file(dir / "config.json")), data.config);
}

TEST(Checkpoint, InferenceOnlyCheckpoint) {
  test::TempDir root;
  CheckpointData data = make_checkpoint(3);
  data.trainer.reset();
  data.model_metadata["format"] = "pt";
  save_checkpoint(root / "infer", data);
  const Checkpoint ckpt = Checkpoint::open(root / "infer/");  // a trailing slash is fine
  EXPECT_FALSE(ckpt.has_trainer_state());
  EXPECT_EQ(ckpt.model().metadata().at("format"), "pt");
  EXPECT_NE(test::error_message([&] { ckpt.step(); }).find("no trainer state"), std::string::npos);
  EXPECT_EQ(entries(root / "infer"), (std::vector<std::string>{"config.json", "model.safetensors"}));
}

TEST(Checkpoint, OverwriteReplacesTheWholeDirectory) {
  test::TempDir root;
  const auto dir = root / "ckpt";
  save_checkpoint(dir, make_checkpoint(1));
  CheckpointData second = make_checkpoint(2);
  second.trainer.reset();
  save_checkpoint(dir, second);
  EXPECT_EQ(entries(root.path()), std::vector<std::string>{"ckpt"});
  const Checkpoint ckpt = Checkpoint::open(dir);
  EXPECT_FALSE(ckpt.has_trainer_state());  // nothing of the first save survives
  EXPECT_EQ(ckpt.config()["saved_at_step"], 2);
}

TEST(Checkpoint, ErrorsNameTheFile) {
  test::TempDir root;
  EXPECT_NE(
      test::error_message([&] { Checkpoint::open(root / "absent"); }).find("absent: no such checkpoint"),
      std::string::npos);

  fs::create_directories(root / "empty");
  EXPECT_NE(test::error_message([&] { Checkpoint::open(root / "empty"); }).find("empty/config.json: missing"),
            std::string::npos);

  save_checkpoint(root / "ckpt", make_checkpoint(1));
  { std::ofstream(root / "ckpt" / "config.json") << "{broken"; }
  EXPECT_NE(
      test::error_message([&] { Checkpoint::open(root / "ckpt"); }).find("ckpt/config.json: invalid JSON"),
      std::string::npos);
  fs::remove(root / "ckpt" / "model.safetensors");
  EXPECT_NE(
      test::error_message([&] { Checkpoint::open(root / "ckpt"); }).find("ckpt/model.safetensors: missing"),
      std::string::npos);

  // A directory of something else is never replaced.
  fs::create_directories(root / "photos");
  std::ofstream(root / "photos" / "cat.jpg") << "meow";
  EXPECT_NE(test::error_message([&] {
              save_checkpoint(root / "photos", make_checkpoint(1));
            }).find("refusing to replace"),
            std::string::npos);
  EXPECT_TRUE(fs::exists(root / "photos" / "cat.jpg"));
  EXPECT_EQ(entries(root.path()), (std::vector<std::string>{"ckpt", "empty", "photos"}));
}

TEST(Checkpoint, InterruptedSaveBetweenRenamesIsRecovered) {
  // The state a kill between "DIR -> DIR.dojo-old" and "tmp -> DIR" leaves behind.
  test::TempDir root;
  const auto dir = root / "ckpt";
  save_checkpoint(dir, make_checkpoint(5));
  fs::rename(dir, root / "ckpt.dojo-old");
  save_checkpoint(root / "scratch", make_checkpoint(6));
  fs::rename(root / "scratch", root / ("ckpt.dojo-tmp-" + std::to_string(999999999)));  // a dead process's

  EXPECT_EQ(open_consistent(dir), 5);
  EXPECT_EQ(Checkpoint::open(dir).dir().filename(), "ckpt.dojo-old");
  save_checkpoint(dir, make_checkpoint(7));  // repairs, then saves
  EXPECT_EQ(open_consistent(dir), 7);
  EXPECT_EQ(entries(root.path()), std::vector<std::string>{"ckpt"});
}

TEST(Checkpoint, RngStateRoundTrip) {
  test::TempDir root;
  torch::manual_seed(123);
  (void)torch::randn({10});
  CheckpointData data = make_checkpoint(1);
  for (auto& item : capture_rng_state()) data.trainer->tensors.push_back(std::move(item));
  const torch::Tensor expected = torch::randn({20});
  save_checkpoint(root / "ckpt", data);

  torch::manual_seed(999);
  const Checkpoint ckpt = Checkpoint::open(root / "ckpt");
  EXPECT_TRUE(ckpt.trainer_tensors().contains("rng.cpu"));
  restore_rng_state(ckpt.trainer_tensors().tensors());
  EXPECT_TRUE(torch::equal(torch::randn({20}), expected));
}

// --- crash safety ---------------------------------------------------------------------------

// Forks a child that saves `data` to `dir` and SIGKILLs itself at crash point number `kill_at`
// (or never, when kill_at < 0). Returns the wait status.
int save_in_child(const fs::path& dir, const CheckpointData& data, int kill_at) {
  return test::run_in_child_killed_at(kill_at, [&] { save_checkpoint(dir, data); });
}

TEST(Checkpoint, KilledAtEveryCrashPointLeavesACompleteCheckpoint) {
  test::TempDir root;
  const auto dir = root / "ckpt";
  const CheckpointData old_data = make_checkpoint(1, 300'000);  // > 1 MiB: several writes per file
  const CheckpointData new_data = make_checkpoint(2, 300'000);

  std::vector<std::string> labels;
  save_checkpoint(dir, old_data);
  set_crash_hook([&](const char* label) { labels.emplace_back(label); });
  save_checkpoint(dir, new_data);
  set_crash_hook(nullptr);
  const auto moved = std::find(labels.begin(), labels.end(), "ckpt:old-moved");
  ASSERT_NE(moved, labels.end());
  ASSERT_GT(labels.size(), 12u);

  for (int kill_at = 0; kill_at < static_cast<int>(labels.size()); ++kill_at) {
    SCOPED_TRACE("killed at crash point " + std::to_string(kill_at) + " (" + labels[kill_at] + ")");
    save_checkpoint(dir, old_data);
    const int status = save_in_child(dir, new_data, kill_at);
    ASSERT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL) << status;

    const int64_t step = open_consistent(dir);
    // Up to the first rename the old checkpoint is the one; once the new one is in place, it is.
    if (kill_at <= moved - labels.begin()) {
      EXPECT_EQ(step, 1);
    }
    if (labels[kill_at] == "ckpt:new-in-place" || labels[kill_at] == "ckpt:done") {
      EXPECT_EQ(step, 2);
    }

    // The next save repairs whatever was left and leaves only DIR behind.
    save_checkpoint(dir, make_checkpoint(3));
    EXPECT_EQ(open_consistent(dir), 3);
    EXPECT_EQ(entries(root.path()), std::vector<std::string>{"ckpt"});
  }
}

TEST(Checkpoint, KilledAtRandomMomentsLeavesACompleteCheckpoint) {
  // A child saves ever newer checkpoints in a loop; it is SIGKILLed at a random moment, and
  // whatever DIR then holds must be one whole checkpoint.
  test::TempDir root;
  const auto dir = root / "ckpt";
  save_checkpoint(dir, make_checkpoint(0));
  std::mt19937 rng(2024);
  int64_t newest = 0;
  for (int round = 0; round < 6; ++round) {
    SCOPED_TRACE("round " + std::to_string(round));
    const int64_t first = newest + 1;
    CheckpointData data = make_checkpoint(first, 1'000'000);  // 4 MB per tensor
    // The child writes a byte after each whole save; the parent waits for the first before its
    // random sleep, so a slow disk cannot make every kill land in a round's first save.
    int saved_pipe[2];
    ASSERT_EQ(::pipe(saved_pipe), 0);
    const pid_t pid = ::fork();
    if (pid == 0) {
      ::close(saved_pipe[0]);
      // Refill the same buffers in place: no ATen kernels run in the forked child.
      for (int64_t step = first;; ++step) {
        data.config["saved_at_step"] = step;
        data.trainer->step = step;
        data.trainer->extra["data_cursor"]["offset"] = step * 7;
        for (auto* list : {&data.model, &data.trainer->tensors}) {
          for (auto& [name, tensor] : *list) {
            if (tensor.scalar_type() == torch::kFloat32) {
              std::fill_n(tensor.data_ptr<float>(), tensor.numel(), static_cast<float>(step));
            } else if (tensor.scalar_type() == torch::kInt64) {
              *tensor.data_ptr<int64_t>() = step;
            } else {
              std::fill_n(tensor.data_ptr<at::BFloat16>(), tensor.numel(),
                          at::BFloat16(static_cast<float>(step)));
            }
          }
        }
        try {
          save_checkpoint(dir, data);
        } catch (...) {
          ::_exit(3);
        }
        if (::write(saved_pipe[1], "s", 1) != 1) ::_exit(4);
      }
    }
    ::close(saved_pipe[1]);
    char saved = 0;
    const bool child_saved = ::read(saved_pipe[0], &saved, 1) == 1;
    std::this_thread::sleep_for(std::chrono::milliseconds(std::uniform_int_distribution<int>(30, 400)(rng)));
    ::kill(pid, SIGKILL);
    int status = 0;
    ::waitpid(pid, &status, 0);
    ::close(saved_pipe[0]);
    ASSERT_TRUE(child_saved) << "the child ended before its first save, status " << status;
    ASSERT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL) << status;
    const int64_t step = open_consistent(dir);
    EXPECT_GE(step, newest);
    newest = step;
  }
  // Every child completed a save before its kill, so the newest whole checkpoint moved on.
  EXPECT_GT(newest, 0);
}

}  // namespace
}  // namespace dojo
