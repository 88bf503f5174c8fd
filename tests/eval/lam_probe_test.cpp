#include "eval/lam_probe.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

namespace dojo::eval {
namespace {

// A commanded trajectory and the pose it produces one step later must give the same per-pair
// motion: pose[t + 1] = cmd[t] (perfect tracking), so pair t moved by cmd[t] - cmd[t - 1].
TEST(LamProbe, CommandAndMeasuredDeltasAlignOnTheSamePair) {
  torch::manual_seed(3);
  const int64_t T = 12;
  const auto cmd = torch::randn({T, 4}).cumsum(0);                               // [T, 4]
  const auto pose = torch::cat({torch::zeros({1, 4}), cmd.slice(0, 0, T - 1)});  // pose[t + 1] = cmd[t]
  const auto c = probe_deltas(cmd, /*commanded=*/true);
  const auto m = probe_deltas(pose, /*commanded=*/false);
  ASSERT_EQ(c.first_pair, 1);
  ASSERT_EQ(c.deltas.size(0), T - 2);
  ASSERT_EQ(m.first_pair, 0);
  ASSERT_EQ(m.deltas.size(0), T - 1);
  EXPECT_TRUE(torch::allclose(c.deltas, m.deltas.slice(0, 1)));
  // The old pairing (cmd[t + 1] - cmd[t] for pair t) is one step ahead of the motion.
  EXPECT_FALSE(torch::allclose((cmd.slice(0, 1) - cmd.slice(0, 0, -1)).slice(0, 1), m.deltas.slice(0, 1)));
}

// A target that is a linear function of the latents is recovered exactly on held-out rows; an
// unrelated target is not.
TEST(LamProbe, RidgeRecoversALinearTargetOnly) {
  torch::manual_seed(5);
  const auto x = torch::randn({200, 8});
  const auto w = torch::randn({8, 3});
  const auto y = x.mm(w) + 0.5;
  const auto r = ridge_probe(x.slice(0, 0, 150), y.slice(0, 0, 150), x.slice(0, 150), y.slice(0, 150), 1e-6);
  EXPECT_GT(r.r2_heldout, 0.999);
  ASSERT_EQ(r.r2_heldout_per_dim.size(), 3u);
  const auto noise = torch::randn({200, 3});
  const auto n =
      ridge_probe(x.slice(0, 0, 150), noise.slice(0, 0, 150), x.slice(0, 150), noise.slice(0, 150));
  EXPECT_LT(n.r2_heldout, 0.1);
}

}  // namespace
}  // namespace dojo::eval
