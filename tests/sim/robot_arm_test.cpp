#include "sim/robot_arm.h"

#include <gtest/gtest.h>

#include <cmath>

namespace dojo::sim::arm {
namespace {

TEST(SimRobotArm, TopDownIkInvertsForwardKinematicsOverTheWorkspace) {
  int solved = 0;
  for (double x = -0.18; x <= 0.2; x += 0.04) {
    for (double y = -0.12; y <= 0.2; y += 0.04) {
      for (double z : {0.02, 0.08, 0.16}) {
        Joints q{};
        ASSERT_TRUE(solve_topdown_ik({x, y, z}, 0.3, &q)) << x << " " << y << " " << z;
        const Point p = forward_grasp_point(q);
        EXPECT_NEAR(p[0], x, 1e-9);
        EXPECT_NEAR(p[1], y, 1e-9);
        EXPECT_NEAR(p[2], z, 1e-9);
        EXPECT_NEAR(q[1] + q[2] + q[3], M_PI, 1e-9);                          // gripper points straight down
        EXPECT_NEAR(std::remainder(q[0] - q[4] - 0.3, 2 * M_PI), 0.0, 1e-9);  // closing direction
        ++solved;
      }
    }
  }
  EXPECT_GT(solved, 200);
}

TEST(SimRobotArm, UnreachableTargetsReportFailureButStayFinite) {
  Joints q{};
  EXPECT_FALSE(solve_topdown_ik({-1.5, 0.9, 0.0}, 0.0, &q));
  for (double v : q) EXPECT_TRUE(std::isfinite(v));
}

TEST(SimRobotArm, BoxClosingYawIsAFaceDirectionNearTheNeutralRoll) {
  const Point p{0.0, 0.05, 0.02};
  for (double box_yaw : {-2.0, -0.4, 0.0, 0.7, 1.9}) {
    const double psi = box_closing_yaw(p, box_yaw);
    EXPECT_NEAR(std::remainder(psi - box_yaw, M_PI / 2), 0.0, 1e-9);
    EXPECT_LE(std::fabs(std::remainder(neutral_closing_yaw(p) - psi, 2 * M_PI)), M_PI / 4 + 1e-9);
  }
}

}  // namespace
}  // namespace dojo::sim::arm
