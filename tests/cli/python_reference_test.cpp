// The Python reference that docs/benchmarks.md times the engine against
// (scripts/python_reference/) must compute the engine's numbers: the same weights, inputs and
// random draws give the same sampling velocity, streamed latents and training step, eager and
// TorchScript. A timing-free run (one step of each kind) on Debian's python3-torch.
#include <gtest/gtest.h>

#include <filesystem>
#include <nlohmann/json.hpp>

#include "test_util.h"

namespace dojo {
namespace {

TEST(PythonReference, ComputesTheEnginesNumbersEagerAndScripted) {
  test::TempDir tmp;
  const auto exported = tmp / "export";
  const auto made = test::run_dojo(
      "-q wm step-speed --repeats 1 --stream-steps 1 --warmup 1 --window 3 --export " + exported.string());
  ASSERT_EQ(made.exit_code, 0) << made.output;
  const auto script =
      std::filesystem::path(DOJO_SOURCE_DIR) / "scripts" / "python_reference" / "step_speed.py";
  for (const char* mode : {"eager", "scripted"}) {
    const auto run = test::run_command(
        "for p in python3 /usr/bin/python3; do $p -c 'import torch' 2>/dev/null && exec $p " +
        script.string() + " " + exported.string() + " --mode " + mode +
        " 2>/dev/null; done; echo 'no python3 with torch' >&2; exit 9");
    ASSERT_EQ(run.exit_code, 0) << mode << ": " << run.output;
    const auto start = run.output.find("{\n  \"mode\"");  // the report, after any tracer warnings
    ASSERT_NE(start, std::string::npos) << run.output;
    const auto report = nlohmann::json::parse(run.output.substr(start));
    const auto& c = report["checks"];
    EXPECT_LT(c["sample_velocity_max_abs_diff"].get<double>(), 1e-4) << mode;
    EXPECT_LT(c["stream_latents_max_abs_diff"].get<double>(), 1e-4) << mode;
    EXPECT_LT(c["train_loss_rel_diff"].get<double>(), 1e-5) << mode;
    EXPECT_LT(c["train_grad_norm_rel_diff"].get<double>(), 1e-4) << mode;
    EXPECT_LT(c["train_weights_max_abs_diff"].get<double>(), 1e-2 * c["train_update_max_abs"].get<double>())
        << mode;
    EXPECT_LT(c["train_ema_max_abs_diff"].get<double>(), 1e-2 * c["train_update_max_abs"].get<double>())
        << mode;
  }
}

}  // namespace
}  // namespace dojo
