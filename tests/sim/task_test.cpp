#include "sim/task.h"

#include <gtest/gtest.h>

#include <cmath>

#include <nlohmann/json.hpp>

#include "core/error.h"
#include "sim/robot_arm.h"

namespace dojo::sim {
namespace {

SceneSpec two_cube_scene() {
  SceneSpec spec = sample_scene(Embodiment::kRobot, {}, 9);
  ObjectSpec a;
  a.size = {0.022, 0.022, 0.022};
  a.pos = {-0.1, 0.0, 0.0};
  ObjectSpec b = a;
  b.pos = {-0.1, -0.08, 0.0};
  spec.objects = {a, b};
  return spec;
}

TEST(SimTask, BinSuccessOnHandSetStates) {
  World w(two_cube_scene());
  const BinSpec& bin = w.spec().bin;
  const double rest_z = 0.004 + 0.022;  // on the bin floor
  EXPECT_DOUBLE_EQ(bin_success(w), 0.0);
  w.set_object_pose(0, {bin.center[0] - 0.03, bin.center[1], rest_z});
  EXPECT_TRUE(object_in_bin(w, 0));
  EXPECT_FALSE(object_in_bin(w, 1));
  EXPECT_DOUBLE_EQ(bin_success(w), 0.5);
  w.set_object_pose(1, {bin.center[0] + 0.03, bin.center[1] + 0.02, rest_z});
  EXPECT_DOUBLE_EQ(bin_success(w), 1.0);
  // They really rest there: still 1.0 after two seconds of physics.
  w.hold(20);
  EXPECT_DOUBLE_EQ(bin_success(w), 1.0);
  // Hovering above the bin does not count; neither does sitting on the wall outside the inner area.
  w.set_object_pose(1, {bin.center[0], bin.center[1], 0.2});
  EXPECT_FALSE(object_in_bin(w, 1));
  EXPECT_DOUBLE_EQ(bin_success(w), 0.5);
  w.set_object_pose(1, {bin.center[0] + bin.half_x + 0.006, bin.center[1], 0.06});
  EXPECT_FALSE(object_in_bin(w, 1));
}

TEST(SimTask, MovingObjectsAreNotResting) {
  World w(two_cube_scene());
  const BinSpec& bin = w.spec().bin;
  w.set_object_pose(0, {bin.center[0], bin.center[1], 0.06});  // in the bin's volume, falling
  w.set_object_pose(1, {bin.center[0] + 0.04, bin.center[1], 0.026});
  w.step(w.last_command());
  EXPECT_TRUE(object_in_bin(w, 0));
  EXPECT_FALSE(object_resting(w, 0));
  EXPECT_DOUBLE_EQ(bin_success(w), 0.5);
  w.hold(15);
  EXPECT_DOUBLE_EQ(bin_success(w), 1.0);
}

TEST(SimTask, HeldObjectsDoNotCount) {
  SceneSpec spec = two_cube_scene();
  spec.objects.resize(1);
  const BinSpec& bin = spec.bin;
  spec.objects[0].pos = {bin.center[0], bin.center[1] - 0.01, 0.0};
  World w(spec);
  w.set_object_pose(0, {bin.center[0], bin.center[1] - 0.01, 0.026});
  w.hold(5);
  EXPECT_DOUBLE_EQ(bin_success(w), 1.0);
  // Close the gripper on it without lifting: touched by the robot, so not counted as placed.
  arm::Joints q{};
  arm::solve_topdown_ik({bin.center[0], bin.center[1] - 0.01, 0.026},
                        arm::box_closing_yaw({bin.center[0], bin.center[1], 0}, 0), &q);
  std::vector<double> c(q.begin(), q.end());
  c.push_back(1.0);
  for (int i = 0; i < 15; ++i) w.step(c);
  c[5] = 0.0;
  for (int i = 0; i < 6; ++i) w.step(c);
  EXPECT_TRUE(w.touching(0));
  EXPECT_DOUBLE_EQ(bin_success(w), 0.0);
}

TEST(SimTask, SceneWithoutBinThrows) {
  SceneSpec spec = sample_scene(Embodiment::kHuman, {}, 1);
  spec.bin.enabled = false;
  World w(spec);
  EXPECT_THROW(bin_success(w), Error);
  EXPECT_FALSE(w.num_objects() > 0 && object_in_bin(w, 0));
}

TEST(SimTask, OutcomesReportDisplacementAndToppling) {
  World w(two_cube_scene());
  const std::vector<ObjectPose> initial = w.object_poses();
  const double s = std::sqrt(0.5);
  w.set_object_pose(0, {-0.02, 0.0, 0.022}, {s, s, 0, 0});
  const nlohmann::json out = object_outcomes(w, initial);
  ASSERT_EQ(out.size(), 2u);
  EXPECT_NEAR(out[0]["displacement"].get<double>(), 0.08, 1e-9);
  EXPECT_NEAR(out[0]["tilt_deg"].get<double>(), 90.0, 1e-6);
  EXPECT_TRUE(out[0]["toppled"].get<bool>());
  EXPECT_FALSE(out[1]["toppled"].get<bool>());
  EXPECT_TRUE(out[1]["on_table"].get<bool>());
  EXPECT_FALSE(out[1]["lifted"].get<bool>());
}

}  // namespace
}  // namespace dojo::sim
