// Helpers shared by the tests: temporary directories, fixture paths, running the CLI.
#pragma once

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <filesystem>
#include <functional>
#include <string>

#include "core/runtime.h"

namespace dojo::test {

// A fresh directory under the system temp dir, removed when the object dies.
class TempDir {
 public:
  TempDir();
  ~TempDir();
  const std::filesystem::path& path() const { return path_; }
  std::filesystem::path operator/(const std::string& name) const { return path_ / name; }

 private:
  std::filesystem::path path_;
};

// tests/golden: the parity fixtures made with the published implementations, and the released
// parameter key lists in keys/ (tests/golden/README.md).
std::filesystem::path golden_dir();
// A real camera clip shipped by Debian's opencv-doc, or "" when not installed.
std::filesystem::path sample_video(const std::string& name = "vtest.avi");

// The largest absolute difference between two tensors, in double; a failure (and infinity) when
// their shapes differ.
double max_abs(const torch::Tensor& a, const torch::Tensor& b);

// The mean of a frame's values (any dtype).
float mean_level(const torch::Tensor& frame);

// The whole content of a file ("" when it cannot be read).
std::string read_file(const std::filesystem::path& path);
// A trainer's loss.csv: the first step's value of its first column after the step (NaN and a
// failure when there is none).
double first_loss_in_curve(const std::filesystem::path& csv);
// Every weight of the checkpoint directory's model.safetensors is float32 (failures name them).
void expect_float32_checkpoint(const std::filesystem::path& dir);
// The message of the dojo::Error that `fn` throws, or "(no error)" when it throws none.
std::string error_message(const std::function<void()>& fn);

struct CommandResult {
  int exit_code;
  std::string output;  // stdout and stderr together
};
// Forks a child that runs `work` and SIGKILLs itself at crash point number `kill_at` of
// core/atomic_file.h (never, when kill_at < 0). The child exits 0 when `work` returns, 3 when it
// throws. Returns the child's wait status.
int run_in_child_killed_at(int kill_at, const std::function<void()>& work);

// Runs a shell command line and waits for it; the output is its stdout and stderr together.
CommandResult run_command(const std::string& command);

// Runs the built `dojo` executable with the given argument string.
CommandResult run_dojo(const std::string& args);

// Holds libtorch at one intra-op thread for a test's scope: on a shared 2-core machine a second
// OpenMP thread competing with other processes makes small ops many times slower, not faster.
class OneThread : public ScopedThreads {
 public:
  OneThread() : ScopedThreads(1) {}
};

}  // namespace dojo::test

// GPU tests are named *_CUDA and start with this line, so they skip cleanly on CPU machines.
#define DOJO_REQUIRE_CUDA()                                                 \
  do {                                                                      \
    if (!torch::cuda::is_available()) GTEST_SKIP() << "CUDA not available"; \
  } while (0)

namespace dojo::test {
// Files written once per test process by tests/core/write_torch_files.py with the system's
// PyTorch (python3-torch): see that script for the list. A missing PyTorch fails the tests that
// ask for them (ADD_FAILURE naming the command), never skips them.
std::filesystem::path torch_files_dir();
// Where those files' malicious payloads would `touch` a marker if anything ran them.
std::filesystem::path torch_files_marker();
// tests/fixtures/dcp: a distributed checkpoint written by PyTorch 2.11 (tests/fixtures/README.md).
std::filesystem::path dcp_fixture_dir();
}  // namespace dojo::test
