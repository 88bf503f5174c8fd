// The trainers' --device and --precision: bf16 (autocast, float32 master weights and checkpoints)
// runs on the CPU here; the *_CUDA tests run the same commands on a GPU and compare with the CPU.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/safetensors.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo {
namespace {

namespace fs = std::filesystem;

nlohmann::json read_json(const fs::path& file) { return nlohmann::json::parse(test::read_file(file)); }

// A tiny robot dataset and the distillation commands on the reference teacher.
class DistillDevice : public ::testing::Test {
 protected:
  void SetUp() override {
    test::SyntheticOptions g;
    g.episodes = 2;
    g.frames = 52;
    g.size = 64;
    test::write_synthetic_dataset(tmp_ / "robot", g);
  }
  // The warm-up into out (3 steps on 4 clips, a 4-step teacher), with `device_args`.
  test::CommandResult warmup(const fs::path& out, const std::string& device_args) {
    return test::run_dojo("--threads 1 distill --data " + (tmp_ / "robot").string() +
                          " --split all --max-clips 4 --teacher-steps 4 --steps 3 --batch 2 " + device_args +
                          " --out " + out.string());
  }
  // Self-Forcing from `init` (2 iterations: a generator then a critic update).
  test::CommandResult self_forcing(const fs::path& init, const fs::path& out,
                                   const std::string& device_args) {
    return test::run_dojo("--threads 1 distill --stage self-forcing --init " +
                          (init / "checkpoint").string() + " --data " + (tmp_ / "robot").string() +
                          " --split all --max-clips 2 --min-frames 4 --max-frames 5 --batch 1 --steps 2 " +
                          device_args + " --out " + out.string());
  }
  test::OneThread one_;
  test::TempDir tmp_;
};

TEST_F(DistillDevice, Bf16WarmupAndSelfForcingRecordThePrecisionAndSaveFloat32) {
  ASSERT_EQ(warmup(tmp_ / "fp32", "").exit_code, 0);
  auto r = warmup(tmp_ / "bf16", "--precision bf16");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto fp32 = read_json(tmp_ / "fp32" / "distill_summary.json");
  const auto bf16 = read_json(tmp_ / "bf16" / "distill_summary.json");
  EXPECT_EQ(bf16.at("precision"), "bf16");
  EXPECT_EQ(bf16.at("device"), "cpu");
  EXPECT_EQ(fp32.at("precision"), "fp32");
  // The teacher's bf16 trajectories are other trajectories: their shards say so.
  const auto shard = SafetensorsFile::open(tmp_ / "bf16" / "trajectories" / "shard-00000.safetensors");
  EXPECT_EQ(nlohmann::json::parse(shard.metadata().at("trajectories")).value("precision", ""), "bf16");
  // Same draws, matmuls in bf16: close to the float32 run, and not secretly float32. The warm-up
  // loss is the student's small distance to its own teacher's x0 (it starts as the teacher), to
  // which bf16's rounding on both sides adds directly: measured 0.0343 against 0.0307 (+12 %).
  const double a = fp32.at("first_loss"), b = bf16.at("first_loss");
  EXPECT_NEAR(b, a, 0.3 * a);
  EXPECT_NE(a, b);
  test::expect_float32_checkpoint(tmp_ / "bf16" / "checkpoint");

  r = self_forcing(tmp_ / "bf16", tmp_ / "sf", "--precision bf16");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto sf = read_json(tmp_ / "sf" / "distill_summary.json");
  EXPECT_EQ(sf.at("precision"), "bf16");
  EXPECT_EQ(sf.at("iterations"), 2);
  EXPECT_TRUE(std::isfinite(sf.at("fixed_batch_latent_mse_end").get<double>()));
  test::expect_float32_checkpoint(tmp_ / "sf" / "checkpoint");
  test::expect_float32_checkpoint(tmp_ / "sf" / "critic");

  r = warmup(tmp_ / "fp16", "--precision fp16");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("fp16"), std::string::npos) << r.output;
}

TEST_F(DistillDevice, OnCudaMatchesTheCpu_CUDA) {
  DOJO_REQUIRE_CUDA();
  ASSERT_EQ(warmup(tmp_ / "cpu", "").exit_code, 0);
  auto r = warmup(tmp_ / "cuda", "--device cuda");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto cpu = read_json(tmp_ / "cpu" / "distill_summary.json");
  const auto cuda = read_json(tmp_ / "cuda" / "distill_summary.json");
  EXPECT_EQ(cuda.at("device"), "cuda:0");
  const double a = cpu.at("fixed_batch_loss_end"), b = cuda.at("fixed_batch_loss_end");
  EXPECT_NEAR(b, a, 1e-3 * a) << "float32 on both: the same draws give the same student";
  // The CUDA student loads and runs on the CPU.
  test::expect_float32_checkpoint(tmp_ / "cuda" / "checkpoint");
  r = self_forcing(tmp_ / "cuda", tmp_ / "sf", "--device cuda --precision bf16");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(read_json(tmp_ / "sf" / "distill_summary.json").at("precision"), "bf16");
  r = self_forcing(tmp_ / "cuda", tmp_ / "sf_cpu", "");
  ASSERT_EQ(r.exit_code, 0) << "a student trained on CUDA goes on on the CPU: " << r.output;
}

// The smaller trainers, each a few steps on a tiny dataset: the command (DATA, OUT and TOK
// replaced), where its checkpoint lands and how its first loss is read.
struct SmallTrainer {
  std::string name, command;
  std::string checkpoint;     // relative to OUT
  bool printed_loss = false;  // the tokenizer prints "recon mse FIRST -> LAST"; the others write loss.csv
};

std::vector<SmallTrainer> small_trainers() {
  return {
      {"probe train", "probe train --data DATA --split all --size 32 --width 8 --steps 3 --batch 4 --out OUT",
       "checkpoint"},
      {"lam train", "lam train --data DATA --model tiny --steps 3 --batch 2 --workers 1 --out OUT",
       "checkpoint"},
      {"tokenizer train",
       "tokenizer train --data DATA --split all --steps 3 --batch 1 --frames 5 --size 32 --dim 8 --workers 1 "
       "--image-fraction 0 --out OUT",
       "", true},
      {"fast decoder",
       "tokenizer fast-decoder --tokenizer TOK --data DATA --split all --max-clips 4 --steps 3 --batch 2 "
       "--out OUT",
       "checkpoint"},
  };
}

std::string replaced(std::string text, const std::string& key, const std::string& value) {
  for (auto at = text.find(key); at != std::string::npos; at = text.find(key, at + value.size()))
    text.replace(at, key.size(), value);
  return text;
}

// The first step's loss of a run into `out`.
double first_loss(const SmallTrainer& t, const fs::path& out, const std::string& output) {
  if (!t.printed_loss) return test::first_loss_in_curve(out / "loss.csv");
  const auto at = output.find("recon mse ");
  EXPECT_NE(at, std::string::npos) << output;
  return at == std::string::npos ? std::nan("") : std::stod(output.substr(at + 10));
}

class SmallTrainerDevice : public ::testing::Test {
 protected:
  void SetUp() override {
    test::SyntheticOptions g;
    g.episodes = 2;
    g.frames = 16;
    g.size = 32;
    // Raw frames: every loader these trainers use (clips, keypoint frames, latent caches) reads
    // them as the trainer build without a video library does.
    g.video_format = data::VideoFormat::kRaw;
    test::write_synthetic_dataset(tmp_ / "data", g);
  }
  // Runs `t` into OUT = tmp/<tag>; returns the command's result.
  test::CommandResult run(const SmallTrainer& t, const std::string& tag, const std::string& device_args) {
    auto command = replaced(t.command, "DATA", (tmp_ / "data").string());
    command = replaced(command, "OUT", (tmp_ / tag).string());
    command =
        replaced(command, "TOK", (fs::path(DOJO_SOURCE_DIR) / "models" / "reference" / "tokenizer").string());
    return test::run_dojo("--threads 1 " + command + " " + device_args);
  }
  // Trains each small trainer with `a` and with `b`; their first losses agree within `tolerance`
  // (relative), and differ when `differ`.
  void compare(const std::string& a, const std::string& b, double tolerance, bool differ) {
    for (const auto& t : small_trainers()) {
      SCOPED_TRACE(t.name);
      const std::string tag = replaced(t.name, " ", "_");
      const auto ra = run(t, tag + "_a", a), rb = run(t, tag + "_b", b);
      ASSERT_EQ(ra.exit_code, 0) << ra.output;
      ASSERT_EQ(rb.exit_code, 0) << rb.output;
      const double la = first_loss(t, tmp_ / (tag + "_a"), ra.output);
      const double lb = first_loss(t, tmp_ / (tag + "_b"), rb.output);
      std::printf("%s: first loss %.6f (%s) vs %.6f (%s)\n", t.name.c_str(), la, a.c_str(), lb, b.c_str());
      EXPECT_NEAR(lb, la, tolerance * std::abs(la));
      if (differ) {
        EXPECT_NE(la, lb) << "the second run was not computed another way";
      }
      test::expect_float32_checkpoint(tmp_ / (tag + "_b") / t.checkpoint);
    }
  }
  test::OneThread one_;
  test::TempDir tmp_;
};

// Same weights, same batches: bf16 matmuls and convolutions give a first loss within a few percent
// of float32's, and not float32's exactly; the checkpoints stay float32.
TEST_F(SmallTrainerDevice, Bf16OnTheCpuTrainsCloseToFloat32AndSavesFloat32) {
  compare("", "--precision bf16", 0.1, /*differ=*/true);
  for (const auto& t : small_trainers()) {
    const auto r = run(t, "fp16", "--precision fp16");
    EXPECT_NE(r.exit_code, 0) << t.name;
    EXPECT_NE(r.output.find(t.name + ": precision fp16 is not supported for training"), std::string::npos)
        << r.output;
  }
}

TEST_F(SmallTrainerDevice, OnCudaTrainsLikeTheCpu_CUDA) {
  DOJO_REQUIRE_CUDA();
  // The posterior samples of the tokenizer and the LAM come from the CUDA generator there.
  compare("", "--device cuda", 0.1, /*differ=*/false);
  compare("--device cuda", "--device cuda --precision bf16", 0.1, /*differ=*/true);
}

}  // namespace
}  // namespace dojo
