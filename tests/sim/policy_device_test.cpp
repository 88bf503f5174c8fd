// `policy train` (behaviour cloning) and `policy detector` on --device / --precision: bf16 on the
// CPU here, CUDA in the *_CUDA test. The second run of each pair trains on the first's rendered
// data (copied in), so the two differ only in how they compute.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "test_util.h"

namespace dojo {
namespace {

namespace fs = std::filesystem;

struct PolicyTrainer {
  std::string name, command;  // OUT replaced; the command's own message prefix
  std::string data;           // the rendered data file beside data.json
};

std::vector<PolicyTrainer> policy_trainers(const fs::path& policy_set) {
  return {
      {"policy train", "policy train --episodes 2 --frames 16 --steps 3 --batch 8 --snapshots 1 --out OUT",
       "demos.safetensors"},
      {"policy detector",
       "policy detector --scenes 2 --steps 3 --policies " + policy_set.string() + " --out OUT",
       "data.safetensors"}};
}

class PolicyDevice : public ::testing::Test {
 protected:
  void SetUp() override {
    std::ofstream(tmp_ / "set.json")
        << R"({"policies": [{"name": "expert"}, {"name": "idle", "behavior": "idle"}]})";
  }
  // Trains each with `a` (rendering its data), then with `b` on a copy of that data; their first
  // losses agree within `tolerance` (relative), differ when `differ`; b's checkpoint is float32.
  void compare(const std::string& a, const std::string& b, double tolerance, bool differ) {
    for (const auto& t : policy_trainers(tmp_ / "set.json")) {
      SCOPED_TRACE(t.name);
      const auto out_a = tmp_ / (t.data + ".a"), out_b = tmp_ / (t.data + ".b");
      const auto command = [&](const fs::path& out) {
        auto c = t.command;
        c.replace(c.find("OUT"), 3, out.string());
        return "--threads 1 " + c + " ";
      };
      auto r = test::run_dojo(command(out_a) + a);
      ASSERT_EQ(r.exit_code, 0) << r.output;
      fs::create_directories(out_b);
      for (const auto& file : {std::string("data.json"), t.data}) fs::copy_file(out_a / file, out_b / file);
      r = test::run_dojo(command(out_b) + b);
      ASSERT_EQ(r.exit_code, 0) << r.output;
      EXPECT_EQ(r.output.find("rendering"), std::string::npos) << "the copied data is used: " << r.output;
      const double la = test::first_loss_in_curve(out_a / "loss.csv");
      const double lb = test::first_loss_in_curve(out_b / "loss.csv");
      std::printf("%s: first loss %.6f (%s) vs %.6f (%s)\n", t.name.c_str(), la, a.c_str(), lb, b.c_str());
      EXPECT_NEAR(lb, la, tolerance * std::abs(la));
      if (differ) {
        EXPECT_NE(la, lb) << "the second run was not computed another way";
      }
      test::expect_float32_checkpoint(out_b / "checkpoint");
    }
  }
  test::TempDir tmp_;
};

TEST_F(PolicyDevice, Bf16OnTheCpuTrainsCloseToFloat32) { compare("", "--precision bf16", 0.1, true); }

TEST_F(PolicyDevice, OnCudaTrainsLikeTheCpu_CUDA) {
  DOJO_REQUIRE_CUDA();
  // cuDNN convolutions may run in TF32 there: agreement within a percent, not bit for bit.
  compare("", "--device cuda", 1e-2, false);
  compare("", "--device cuda --precision bf16", 0.1, true);
}

}  // namespace
}  // namespace dojo
