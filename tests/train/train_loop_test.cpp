// The training loop's roofline: one steady step's matrix products counted, timed alone after the
// run, and set against the steady steps' time.
#include "train/train_loop.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <chrono>
#include <thread>

#include "test_util.h"

namespace dojo::train {
namespace {

LoopResult run_steps(int64_t steps, bool roofline, const std::function<void()>& work) {
  LoopOptions o;
  o.name = "loop test";
  o.steps = steps;
  o.progress = false;
  o.roofline = roofline;
  return run_training_loop(
      o, 0,
      [&](const LoopStep&) {
        work();
        return StepRecord{{}, 1, ""};
      },
      [](int64_t, bool) {});
}

TEST(TrainLoop, SetsTheStepsAgainstTheirOwnMatrixProducts) {
  test::OneThread one_thread;
  torch::NoGradGuard no_grad;
  const auto a = torch::randn({192, 192}), b = torch::randn({192, 192});
  // One step's products are counted (8 a step, whatever the run's length), the steady steps'
  // time is set against their time alone. Timing itself is not asserted: CI runs tests side by side.
  const auto run = run_steps(6, true, [&] {
    for (int i = 0; i < 8; ++i) (void)torch::mm(a, b);
    (void)(a + b).sum();  // not a product
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  });
  EXPECT_EQ(run.products, 8);
  EXPECT_DOUBLE_EQ(run.products_flops, 8 * 2.0 * 192 * 192 * 192);
  EXPECT_GE(run.step_seconds, 0.005);  // the counted step, slowed by the census, is not among these
  EXPECT_GT(run.products_seconds_alone, 0);
  EXPECT_DOUBLE_EQ(run.roofline_fraction, run.products_seconds_alone / run.step_seconds);
  // Off, or too few steps to keep one steady step out of the throughput: not measured.
  const auto off = run_steps(6, false, [&] { (void)torch::mm(a, b); });
  EXPECT_EQ(off.products, 0);
  EXPECT_EQ(off.roofline_fraction, 0);
  EXPECT_EQ(run_steps(3, true, [&] { (void)torch::mm(a, b); }).roofline_fraction, 0);
}

}  // namespace
}  // namespace dojo::train
