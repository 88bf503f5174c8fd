#include "core/torch_file.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <random>

#include "core/error.h"
#include "test_util.h"
#include "torch_file_replay.h"

namespace dojo {
namespace {

namespace fs = std::filesystem;

torch::ScalarType dtype_named(const std::string& name) { return pickled_scalar_type("torch." + name); }

// Every tensor of a file written by tests/core/write_torch_files.py against its expected.json.
void expect_tensors_match(const fs::path& file) {
  const auto expected = nlohmann::json::parse(test::read_file(test::torch_files_dir() / "expected.json"));
  const TorchFile torch_file = TorchFile::open(file);
  const NamedTensors tensors = torch_file.tensors();
  ASSERT_EQ(tensors.size(), expected.size()) << file;
  for (const auto& [name, t] : tensors) {
    ASSERT_TRUE(expected.contains(name)) << name;
    const auto& e = expected[name];
    EXPECT_EQ(t.scalar_type(), dtype_named(e["dtype"])) << name;
    EXPECT_EQ(t.sizes().vec(), e["shape"].get<std::vector<int64_t>>()) << name;
    const auto values = e["values"].get<std::vector<double>>();
    const torch::Tensor want = torch::tensor(values, torch::kFloat64).reshape(t.sizes());
    if (t.numel() > 0) {
      EXPECT_TRUE(torch::equal(t.to(torch::kFloat64), want)) << name << " in " << file;
    }
  }
}

TEST(TorchFile, ZipArchivesGiveEveryDtypeShapeAndValue) {
  const auto file = test::torch_files_dir() / "tensors_zip.pt";
  expect_tensors_match(file);
  EXPECT_EQ(TorchFile::open(file).format(), "zip");
}

TEST(TorchFile, LegacyFilesGiveEveryDtypeShapeAndValue) {
  const auto file = test::torch_files_dir() / "tensors_legacy.pt";
  expect_tensors_match(file);
  EXPECT_EQ(TorchFile::open(file).format(), "legacy");
}

TEST(TorchFile, ViewsShareTheirStorageWithOffsetsAndStrides) {
  for (const char* name : {"tensors_zip.pt", "tensors_legacy.pt"}) {
    const TorchFile file = TorchFile::open(test::torch_files_dir() / name);
    auto base = file.tensor(file.at("base"));
    const auto rows = file.tensor(file.at("rows_1_to_3"));
    const auto transposed = file.tensor(file.at("transposed"));
    EXPECT_EQ(transposed.strides().vec(), (std::vector<int64_t>{1, 6})) << name;
    EXPECT_EQ(rows.storage_offset(), 6) << name;
    // One storage: a write through the base shows in the views, never in the file.
    base.index_put_({1, 0}, 1234.5f);
    EXPECT_EQ(rows.index({0, 0}).item<float>(), 1234.5f) << name;
    EXPECT_EQ(transposed.index({0, 1}).item<float>(), 1234.5f) << name;
    const TorchFile again = TorchFile::open(test::torch_files_dir() / name);
    EXPECT_NE(again.tensor(again.at("base")).index({1, 0}).item<float>(), 1234.5f) << name;
  }
}

TEST(TorchFile, LightningCheckpointGivesItsStateDictAndSkipsTheRest) {
  const TorchFile file = TorchFile::open(test::torch_files_dir() / "lightning.ckpt");
  EXPECT_EQ(file.at("epoch").integer, 3);
  const auto state = file.tensors("state_dict");
  const auto golden = SafetensorsFile::open(test::golden_dir() / "lam_tiny_weights.safetensors");
  ASSERT_EQ(state.size(), golden.keys().size());
  for (const auto& [name, t] : state) EXPECT_TRUE(torch::equal(t, golden.tensor(name))) << name;
  // The optimizer's tensors are in the file and reachable by path, but not in the state dict.
  EXPECT_EQ(file.tensor(file.at("optimizer_states.0.state.0.step")).item<float>(), 5.0f);
  EXPECT_NE(test::error_message([&] {
              file.at("state_dict.lam.nothing");
            }).find("no entry 'state_dict.lam.nothing'"),
            std::string::npos);
}

TEST(TorchFile, MaliciousFilesAreRefusedWithTheGlobalNamedAndNothingRuns) {
  const auto dir = test::torch_files_dir();
  const auto marker = test::torch_files_marker();
  // Control: Python's own loader runs the payload (so these files would do harm) unless told
  // weights_only, which PyTorch >= 2.6 defaults to and which refuses such files too.
  fs::remove(marker);
  const auto python = test::run_command(
      "for p in python3 /usr/bin/python3; do $p -c 'import torch' 2>/dev/null && exec $p -c \"import torch; "
      "torch.load('" +
      (dir / "evil_os_system.pt").string() + "', weights_only=False)\"; done");
  EXPECT_TRUE(fs::exists(marker)) << "torch.load did not run the payload: " << python.output;
  fs::remove(marker);

  const std::vector<std::pair<std::string, std::string>> files = {
      {"evil_os_system.pt", "posix.system"},
      {"evil_builtins_eval.pt", "builtins.eval"},
      {"evil_subprocess_popen.pt", "subprocess.Popen"},
      {"evil_other_global.pt", "shutil.rmtree"},
      {"evil_legacy.pt", "posix.system"},
  };
  for (const auto& [name, global] : files) {
    const std::string message = test::error_message([&] { TorchFile::open(dir / name); });
    EXPECT_NE(message.find("refuses global '" + global + "'"), std::string::npos) << message;
    EXPECT_NE(message.find(name), std::string::npos) << message;
    EXPECT_EQ(message.find('\n'), std::string::npos) << message;
  }
  EXPECT_FALSE(fs::exists(marker)) << "a payload ran";
  // A name the user allows is read as an inert record: still nothing runs.
  TorchFileOptions allow;
  allow.extra_globals = {"posix.system"};
  const TorchFile file = TorchFile::open(dir / "evil_os_system.pt", allow);
  EXPECT_EQ(file.at("payload").describe(), "object of posix.system");
  EXPECT_EQ(file.tensors().size(), 1u);
  EXPECT_FALSE(fs::exists(marker)) << "a payload ran";
}

TEST(TorchFile, RefusesWhatIsNotATorchFileInOneLine) {
  test::TempDir tmp;
  const auto write = [&](const std::string& name, const std::string& bytes) {
    std::ofstream(tmp / name, std::ios::binary) << bytes;
    return tmp / name;
  };
  EXPECT_NE(
      test::error_message([&] { TorchFile::open(write("text.pt", "hello")); }).find("neither a torch.save"),
      std::string::npos);
  EXPECT_NE(test::error_message([&] { TorchFile::open(tmp / "missing.pt"); }).find("missing.pt"),
            std::string::npos);
  EXPECT_NE(test::error_message([&] {
              TorchFile::open(write("pickle.pt", "\x80\x02K\x01."));
            }).find("not a torch.save file"),
            std::string::npos);
}

// Truncations, byte flips and splices of real files: each must read or fail with dojo::Error.
TEST(TorchFile, MutatedFilesReadOrFailCleanly) {
  test::OneThread one_thread;
  const auto dir = test::torch_files_dir();
  std::mt19937 rng(1234);
  int failed = 0, read = 0;
  for (const char* name : {"tensors_zip.pt", "tensors_legacy.pt", "values_p2.pkl", "values_p4.pkl"}) {
    const std::string original = test::read_file(dir / name);
    ASSERT_FALSE(original.empty()) << name;
    for (size_t cut = 0; cut < original.size(); cut += std::max<size_t>(1, original.size() / 97))
      (fuzz::replay_torch_file_input(original.substr(0, cut)) ? read : failed)++;
    for (int round = 0; round < 300; ++round) {
      std::string bytes = original;
      const int flips = 1 + static_cast<int>(rng() % 8);
      for (int i = 0; i < flips; ++i) bytes[rng() % bytes.size()] = static_cast<char>(rng() & 0xff);
      (fuzz::replay_torch_file_input(bytes) ? read : failed)++;
    }
  }
  const std::string metadata =
      test::read_file(test::dcp_fixture_dir() / "checkpoints" / "iter_000000010" / "model" / ".metadata");
  for (size_t cut = 0; cut < metadata.size(); cut += 577)
    fuzz::replay_torch_file_input(metadata.substr(0, cut));
  EXPECT_GT(failed, 0);
  EXPECT_GT(read, 0);
}

// The committed fuzz corpus (fuzz/corpus/torch_file/): every input reads or fails cleanly.
TEST(TorchFile, FuzzCorpusReadsOrFailsCleanly) {
  const auto corpus = fs::path(DOJO_SOURCE_DIR) / "fuzz" / "corpus" / "torch_file";
  ASSERT_TRUE(fs::is_directory(corpus)) << corpus;
  int inputs = 0;
  for (const auto& entry : fs::recursive_directory_iterator(corpus)) {
    if (!entry.is_regular_file() || entry.path().filename() == "README.md") continue;
    fuzz::replay_torch_file_input(test::read_file(entry.path()));
    ++inputs;
  }
  EXPECT_GT(inputs, 10);
}

}  // namespace
}  // namespace dojo
