#include "test_util.h"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include "core/atomic_file.h"

#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iterator>
#include <limits>
#include <random>

#include "core/error.h"
#include "core/safetensors.h"

namespace dojo::test {

TempDir::TempDir() {
  std::random_device rd;
  path_ = std::filesystem::temp_directory_path() /
          ("dojo_test_" + std::to_string(getpid()) + "_" + std::to_string(rd()));
  std::filesystem::create_directories(path_);
}

TempDir::~TempDir() {
  std::error_code ec;
  std::filesystem::remove_all(path_, ec);
}

std::filesystem::path golden_dir() { return std::filesystem::path(DOJO_SOURCE_DIR) / "tests" / "golden"; }

std::filesystem::path sample_video(const std::string& name) {
  const std::filesystem::path path = "/usr/share/doc/opencv-doc/examples/data/" + name;
  return std::filesystem::exists(path) ? path : std::filesystem::path();
}

double max_abs(const torch::Tensor& a, const torch::Tensor& b) {
  EXPECT_EQ(a.sizes(), b.sizes());
  if (a.sizes() != b.sizes()) return std::numeric_limits<double>::infinity();
  return (a.to(torch::kDouble) - b.to(torch::kDouble)).abs().max().item<double>();
}

float mean_level(const torch::Tensor& frame) { return frame.to(torch::kFloat32).mean().item<float>(); }

std::string read_file(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

double first_loss_in_curve(const std::filesystem::path& csv) {
  const auto text = read_file(csv);
  const auto row = text.find('\n');                                             // the header's end
  const auto comma = row == std::string::npos ? row : text.find(',', row + 1);  // past the step
  if (comma == std::string::npos) {
    ADD_FAILURE() << csv.string() << " holds no step";
    return std::nan("");
  }
  return std::stod(text.substr(comma + 1));
}

void expect_float32_checkpoint(const std::filesystem::path& dir) {
  auto f = SafetensorsFile::open(dir / "model.safetensors");
  for (const auto& key : f.keys()) {
    const auto& dtype = f.info(key).dtype;
    // Integer and boolean tensors (counters, masks) are not weights.
    if (dtype[0] == 'F' || dtype == "BF16") {
      EXPECT_EQ(dtype, "F32") << dir.string() << ": " << key;
    }
  }
}

std::string error_message(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e.what();
  }
  return "(no error)";
}

int run_in_child_killed_at(int kill_at, const std::function<void()>& work) {
  const pid_t pid = ::fork();
  if (pid == 0) {
    int seen = 0;
    set_crash_hook([&](const char*) {
      if (seen++ == kill_at) ::raise(SIGKILL);
    });
    try {
      work();
    } catch (...) {
      ::_exit(3);
    }
    ::_exit(0);
  }
  int status = 0;
  ::waitpid(pid, &status, 0);
  return status;
}

CommandResult run_command(const std::string& command) {
  CommandResult result{-1, ""};
  FILE* pipe = popen((command + " 2>&1").c_str(), "r");
  if (!pipe) return result;
  std::array<char, 4096> buffer;
  size_t n;
  while ((n = fread(buffer.data(), 1, buffer.size(), pipe)) > 0) result.output.append(buffer.data(), n);
  const int status = pclose(pipe);
  result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return result;
}

CommandResult run_dojo(const std::string& args) { return run_command(std::string(DOJO_EXE) + " " + args); }

}  // namespace dojo::test

namespace dojo::test {

namespace {
struct TorchFiles {
  TempDir dir;
  std::filesystem::path marker;
  bool ok = false;
  std::string output;
  TorchFiles() {
    marker = dir / "payload_ran";
    std::filesystem::create_directories(dir / "files");
    const auto script = std::filesystem::path(DOJO_SOURCE_DIR) / "tests" / "core" / "write_torch_files.py";
    // The first interpreter that has torch: $DOJO_PYTHON, python3 on PATH, then Debian's own (a
    // python3 earlier on PATH, e.g. from pyenv, may lack the python3-torch package).
    std::string python;
    for (const std::string candidate :
         {std::getenv("DOJO_PYTHON") ? std::getenv("DOJO_PYTHON") : "", "python3", "/usr/bin/python3"})
      if (!candidate.empty() && run_command(candidate + " -c 'import torch'").exit_code == 0) {
        python = candidate;
        break;
      }
    if (python.empty()) {
      output = "no python3 with torch found ($DOJO_PYTHON, python3, /usr/bin/python3)";
      return;
    }
    const auto result = run_command(python + " " + script.string() + " " + (dir / "files").string() + " " +
                                    marker.string() + " " + golden_dir().string());
    ok = result.exit_code == 0;
    output = result.output;
  }
};
TorchFiles& torch_files() {
  static TorchFiles files;
  return files;
}
}  // namespace

std::filesystem::path torch_files_dir() {
  auto& files = torch_files();
  if (!files.ok)
    ADD_FAILURE() << "tests/core/write_torch_files.py failed (python3-torch installed?): " << files.output;
  return files.dir / "files";
}

std::filesystem::path torch_files_marker() { return torch_files().marker; }

std::filesystem::path dcp_fixture_dir() {
  return std::filesystem::path(DOJO_SOURCE_DIR) / "tests" / "fixtures" / "dcp";
}

}  // namespace dojo::test
