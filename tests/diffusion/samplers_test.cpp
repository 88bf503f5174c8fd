#include "diffusion/samplers.h"

#include <torch/torch.h>

#include <cmath>
#include <optional>

#include "core/error.h"
#include "core/safetensors.h"
#include "test_util.h"

namespace dojo::diffusion {

namespace {

// A missing fixture fails the test that asks for it, naming the file: golden tests never skip
// (tests/golden/README.md).
std::optional<SafetensorsFile> open_fixture() {
  const auto path = test::golden_dir() / "flow_sampler.safetensors";
  if (!std::filesystem::exists(path)) {
    ADD_FAILURE() << path << " is missing: golden fixtures are never skipped (tests/golden/README.md)";
    return std::nullopt;
  }
  return SafetensorsFile::open(path);
}

// The fixture's analytic field: v = 0.5·x + (−1 + 0.8·τ)·k, τ = timestep·0.001 (Python floats).
VelocityFn fixture_velocity(const torch::Tensor& k, std::vector<torch::Tensor>* seen = nullptr) {
  return [k, seen](const torch::Tensor& x, double, int64_t timestep) {
    const double tau = static_cast<double>(timestep) * 0.001;
    auto v = 0.5 * x + (-1.0 + 0.8 * tau) * k;
    if (seen) seen->push_back(v);
    return v;
  };
}

}  // namespace

TEST(Sampler, ScheduleMatchesPublished35StepList) {
  const auto s = flow_sigma_schedule(35, 5.0);
  const std::vector<int64_t> expected = {999, 993, 987, 981, 974, 967, 960, 952, 943, 935, 925, 915,
                                         905, 894, 882, 869, 855, 840, 824, 807, 789, 768, 746, 722,
                                         695, 666, 633, 596, 555, 508, 454, 391, 318, 232, 128};
  EXPECT_EQ(s.timesteps, expected);
  ASSERT_EQ(s.sigmas.size(), 36u);
  EXPECT_EQ(s.sigmas.back(), 0.0);
  EXPECT_NEAR(s.sigmas.front(), 5 * 0.999 / (1 + 4 * 0.999), 1e-7);
  // Decreasing; the truncated timestep never exceeds 1000σ.
  for (int i = 0; i < 35; ++i) {
    EXPECT_GT(s.sigmas[i], s.sigmas[i + 1]);
    EXPECT_LE(static_cast<double>(s.timesteps[i]), 1000 * s.sigmas[i] + 1e-3);
  }
  EXPECT_THROW(flow_sigma_schedule(0, 5.0), Error);
}

TEST(Sampler, ScheduleMatchesFixture) {
  auto f = open_fixture();
  ASSERT_TRUE(f) << "golden fixture missing from " << test::golden_dir();
  const auto s = flow_sigma_schedule(35, 5.0);
  const auto ts = f->tensor("unipc_timesteps");
  const auto sig = f->tensor("unipc_sigmas");
  ASSERT_EQ(ts.numel(), 35);
  ASSERT_EQ(sig.numel(), 36);
  for (int i = 0; i < 35; ++i) EXPECT_EQ(s.timesteps[i], ts[i].item<int64_t>()) << i;
  double err = 0;
  for (int i = 0; i < 36; ++i) err = std::max(err, std::abs(s.sigmas[i] - sig[i].item<double>()));
  EXPECT_LE(err, 1e-7);
  std::cout << "schedule parity: timesteps exact, sigmas max abs " << err << "\n";
}

TEST(Sampler, UniPCMatchesFixtureTrajectory) {
  auto f = open_fixture();
  ASSERT_TRUE(f) << "golden fixture missing from " << test::golden_dir();
  const auto noise = f->tensor("noise", true);
  const auto k = f->tensor("field_k", true);
  const auto latents = f->tensor("unipc_latents");
  const auto x0_ref = f->tensor("unipc_x0_pred");
  const auto v_ref = f->tensor("unipc_velocity");

  FlowSampler sampler(flow_sigma_schedule(35, 5.0), Solver::kUniPC);
  EXPECT_THROW(sampler.last_x0_pred(), Error);
  const auto velocity = fixture_velocity(k);
  auto x = noise;
  double err_latent = 0, err_x0 = 0, err_v = 0;
  for (int i = 0; i < sampler.num_steps(); ++i) {
    const auto v = velocity(x, sampler.sigma(i), sampler.timestep(i));
    err_v = std::max(err_v, test::max_abs(v, v_ref[i]));
    x = sampler.step(x, v);
    err_x0 = std::max(err_x0, test::max_abs(sampler.last_x0_pred(), x0_ref[i]));
    err_latent = std::max(err_latent, test::max_abs(x, latents[i + 1]));
  }
  EXPECT_LE(err_v, 2e-5);
  EXPECT_LE(err_x0, 2e-5);
  EXPECT_LE(err_latent, 2e-5);
  std::cout << "UniPC parity max abs: latents " << err_latent << ", x0_pred " << err_x0 << ", velocity "
            << err_v << "\n";
  EXPECT_THROW(sampler.step(x, x), Error);  // all steps done
}

TEST(Sampler, EulerMatchesFixtureTrajectory) {
  auto f = open_fixture();
  ASSERT_TRUE(f) << "golden fixture missing from " << test::golden_dir();
  const auto noise = f->tensor("noise", true);
  const auto k = f->tensor("field_k", true);
  const auto latents = f->tensor("euler_latents");
  std::vector<torch::Tensor> trajectory;
  int calls = 0;
  const auto out = sample_flow(fixture_velocity(k), noise, flow_sigma_schedule(35, 5.0), Solver::kEuler,
                               &trajectory, [&](int i) { EXPECT_EQ(i, calls++); });
  EXPECT_EQ(calls, 35);
  ASSERT_EQ(trajectory.size(), 36u);
  double err = 0;
  for (int i = 0; i < 36; ++i) err = std::max(err, test::max_abs(trajectory[i], latents[i]));
  EXPECT_LE(err, 2e-5);
  EXPECT_TRUE(out.equal(trajectory.back()));
  std::cout << "Euler parity max abs: " << err << "\n";
}

TEST(Sampler, BatchedUniPCEqualsPerSampleRuns) {
  auto f = open_fixture();
  ASSERT_TRUE(f) << "golden fixture missing from " << test::golden_dir();
  const auto noise = f->tensor("noise", true);
  const auto k = f->tensor("field_k", true);
  // Batch of 3: the fixture sample, a scaled copy and a fresh draw; the field is per-sample affine.
  torch::manual_seed(3);
  const auto batch_noise = torch::cat({noise, 0.5 * noise, torch::randn_like(noise)});  // [3, 16, 2, 4, 4]
  const auto batch_k = torch::cat({k, k, -k});
  const auto schedule = flow_sigma_schedule(12, 5.0);
  std::vector<torch::Tensor> traj;
  const auto batched = sample_flow(fixture_velocity(batch_k), batch_noise, schedule, Solver::kUniPC, &traj);
  EXPECT_EQ(traj.size(), 13u);
  for (int b = 0; b < 3; ++b) {
    const auto single = sample_flow(fixture_velocity(batch_k.narrow(0, b, 1)), batch_noise.narrow(0, b, 1),
                                    schedule, Solver::kUniPC);
    EXPECT_LE(test::max_abs(single, batched.narrow(0, b, 1)), 1e-6) << b;
  }
  // The full fixture run through sample_flow ends at the fixture's final latent.
  const auto full = sample_flow(fixture_velocity(k), noise, flow_sigma_schedule(35, 5.0), Solver::kUniPC);
  EXPECT_LE(test::max_abs(full, f->tensor("unipc_latents")[35]), 2e-5);
}

TEST(Sampler, SolversRecoverX0OfAStraightFlow) {
  // For data x0 and noise ε the true velocity along the straight path is constant: v = ε − x0.
  // Given the exact velocity (from x and σ: v = (x − x0)/σ), both solvers land on x0.
  torch::manual_seed(0);
  const auto x0 = torch::randn({2, 4, 3, 2, 2});
  const auto eps = torch::randn({2, 4, 3, 2, 2});
  const VelocityFn exact = [&](const torch::Tensor& x, double sigma, int64_t) { return (x - x0) / sigma; };
  const auto schedule = flow_sigma_schedule(10, 5.0);
  const auto start = schedule.sigmas[0] * eps + (1 - schedule.sigmas[0]) * x0;
  for (auto solver : {Solver::kEuler, Solver::kUniPC}) {
    const auto out = sample_flow(exact, start, schedule, solver);
    EXPECT_LE(test::max_abs(out, x0), 1e-5);
  }
}

TEST(Sampler, StudentScheduleMatchesFixture) {
  auto f = open_fixture();
  ASSERT_TRUE(f) << "golden fixture missing from " << test::golden_dir();
  const auto exact = student_schedule(false);
  const auto bf16 = student_schedule(true);
  ASSERT_EQ(exact.size(), 4u);
  ASSERT_EQ(bf16.size(), 4u);
  const auto t = f->tensor("student_trigflow_t");
  const auto rf = f->tensor("student_rf_sigma");
  const auto t_bf16 = f->tensor("student_trigflow_t_bf16");
  for (int i = 0; i < 4; ++i) {
    EXPECT_NEAR(exact[i].trigflow_t, t[i].item<double>(), 1e-12) << i;
    EXPECT_NEAR(exact[i].rf_sigma, rf[i].item<double>(), 1e-12) << i;
    EXPECT_NEAR(exact[i].c_skip, f->tensor("student_f64_c_skip")[i].item<double>(), 1e-12) << i;
    EXPECT_NEAR(exact[i].c_out, f->tensor("student_f64_c_out")[i].item<double>(), 1e-12) << i;
    EXPECT_NEAR(exact[i].c_in, f->tensor("student_f64_c_in")[i].item<double>(), 1e-12) << i;
    EXPECT_NEAR(exact[i].c_noise, f->tensor("student_f64_c_noise")[i].item<double>(), 1e-12) << i;
    EXPECT_NEAR(bf16[i].trigflow_t, t_bf16[i].item<double>(), 1e-7) << i;
    EXPECT_NEAR(bf16[i].c_skip, f->tensor("student_bf16_c_skip")[i].item<double>(), 1e-7) << i;
    EXPECT_NEAR(bf16[i].c_out, f->tensor("student_bf16_c_out")[i].item<double>(), 1e-7) << i;
    EXPECT_NEAR(bf16[i].c_in, f->tensor("student_bf16_c_in")[i].item<double>(), 1e-7) << i;
    EXPECT_NEAR(bf16[i].c_noise, f->tensor("student_bf16_c_noise")[i].item<double>(), 1e-7) << i;
  }
  EXPECT_NEAR(student_t_cond(), f->tensor("student_t_cond")[0].item<double>(), 1e-12);
}

TEST(Sampler, StudentScheduleHandValues) {
  const auto s = student_schedule(false);
  const double expected_sigma[4] = {1.0, 0.9375, 5.0 / 6.0, 0.625};
  for (int i = 0; i < 4; ++i) {
    EXPECT_NEAR(s[i].rf_sigma, expected_sigma[i], 1e-12) << i;
    // x0 = c_skip·x_t + c_out·v with v = ε − x0 recovers x0 from the TrigFlow state.
    const double x0 = 0.3, eps = -1.2;
    const double x_t = std::cos(s[i].trigflow_t) * x0 + std::sin(s[i].trigflow_t) * eps;
    EXPECT_NEAR(s[i].c_skip * x_t + s[i].c_out * (eps - x0), x0, 1e-12) << i;
  }
  const auto b = student_schedule(true);
  const double bf16_t[4] = {1.5703125, 1.5078125, 1.375, 1.03125};  // self_forcing.md §3.1
  for (int i = 0; i < 4; ++i) EXPECT_EQ(b[i].trigflow_t, bf16_t[i]) << i;
}

}  // namespace dojo::diffusion
