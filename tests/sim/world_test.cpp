#include "sim/world.h"

#include <gtest/gtest.h>
#include <mujoco/mujoco.h>

#include <cmath>
#include <cstring>

#include "core/error.h"
#include "sim/robot_arm.h"
#include "sim/skills.h"

namespace dojo::sim {
namespace {

bool all_finite(const World& w) {
  const mjModel* m = w.model();
  const mjData* d = w.data();
  for (int i = 0; i < m->nq; ++i) {
    if (!std::isfinite(d->qpos[i])) return false;
  }
  for (int i = 0; i < m->nv; ++i) {
    if (!std::isfinite(d->qvel[i])) return false;
  }
  return true;
}

std::vector<double> robot_command(const arm::Point& p, double gripper) {
  arm::Joints q{};
  arm::solve_topdown_ik(p, 0.0, &q);
  std::vector<double> c(q.begin(), q.end());
  c[4] = 0.0;
  c.push_back(gripper);
  return c;
}

TEST(SimWorld, ObjectsSettleOnTheTableAndStay) {
  for (Embodiment e : {Embodiment::kHuman, Embodiment::kRobot}) {
    SceneSampling opt;
    opt.min_objects = opt.max_objects = 4;
    for (uint64_t seed = 0; seed < 6; ++seed) {
      World w(sample_scene(e, opt, seed));
      w.hold(5);
      const std::vector<ObjectPose> before = w.object_poses();
      w.hold(30);  // 3 s more
      for (int i = 0; i < w.num_objects(); ++i) {
        const ObjectPose now = w.object_pose(i);
        const std::string what = object_description(w.spec().objects[i]) + " seed " + std::to_string(seed);
        EXPECT_LT(std::hypot(now.pos[0] - before[i].pos[0], now.pos[1] - before[i].pos[1]), 0.003) << what;
        EXPECT_LT(std::fabs(now.pos[2] - before[i].pos[2]), 0.003) << what;
        EXPECT_NEAR(w.object_z_range(i)[0], 0.0, 0.004) << what;  // resting on the table top
        EXPECT_LT(std::hypot(now.linvel[0], now.linvel[1], now.linvel[2]), 0.01) << what;
      }
    }
  }
}

TEST(SimWorld, LongRandomMotionStaysFinite) {
  SceneSampling opt;
  opt.min_objects = opt.max_objects = 3;
  World robot(sample_scene(Embodiment::kRobot, opt, 3));
  RobotPolicyOptions random;
  random.behavior = RobotBehavior::kRandomMotion;
  auto rc = make_robot_controller(robot, random, 3);
  World human(sample_scene(Embodiment::kHuman, opt, 3));
  auto hc = make_human_controller(human, {}, 3);
  for (int t = 0; t < 400; ++t) {  // 40 s of each
    robot.step(rc->act(robot, t));
    human.step(hc->act(human, t));
  }
  EXPECT_TRUE(all_finite(robot));
  EXPECT_TRUE(all_finite(human));
  EXPECT_NEAR(robot.sim_time(), 40.0, 1e-6);
  for (const World* w : {&robot, &human}) {
    for (int i = 0; i < w->num_objects(); ++i) EXPECT_GT(w->object_z_range(i)[0], -0.8);  // nothing tunnelled
  }
}

TEST(SimWorld, RobotTracksJointTargets) {
  World w(sample_scene(Embodiment::kRobot, {}, 1));
  for (const arm::Point& p :
       {arm::Point{0.0, 0.0, 0.1}, arm::Point{-0.15, 0.1, 0.05}, arm::Point{0.16, 0.14, 0.16}}) {
    const std::vector<double> c = robot_command(p, 1.0);
    for (int i = 0; i < 15; ++i) w.step(c);
    const Vec3 g = w.grasp_point();
    EXPECT_LT(std::hypot(g[0] - p[0], g[1] - p[1], g[2] - p[2]), 0.004);
    const std::vector<double> s = w.state();
    for (int j = 0; j < 5; ++j) EXPECT_NEAR(s[j], c[j], 0.01);
    EXPECT_NEAR(s[5], 1.0, 0.02);
  }
}

// Scripted top-down pick: the object must come up with the gripper and stay there.
TEST(SimWorld, RobotGraspHoldsCubeAndCylinder) {
  for (Shape shape : {Shape::kBox, Shape::kCylinder}) {
    SceneSpec spec = sample_scene(Embodiment::kRobot, {}, 5);
    ObjectSpec o;
    o.shape = shape;
    o.size = shape == Shape::kBox ? Vec3{0.023, 0.023, 0.023} : Vec3{0.021, 0.03, 0.0};
    o.mass = 0.15;
    o.pos = {-0.05, 0.02, 0.0};
    o.yaw = 0.0;
    spec.objects = {o};
    World w(spec);
    w.hold(5);
    const double h = object_half_height(o);
    const double yaw = shape == Shape::kBox ? arm::box_closing_yaw({o.pos[0], o.pos[1], h}, 0.0)
                                            : arm::neutral_closing_yaw({o.pos[0], o.pos[1], h});
    auto cmd = [&](double z, double grip) {
      arm::Joints q{};
      arm::solve_topdown_ik({o.pos[0], o.pos[1], z}, yaw, &q);
      std::vector<double> c(q.begin(), q.end());
      c.push_back(grip);
      return c;
    };
    for (int i = 0; i < 15; ++i) w.step(cmd(h + 0.1, 1.0));
    for (int i = 0; i < 10; ++i) w.step(cmd(h, 1.0));
    for (int i = 0; i < 6; ++i) w.step(cmd(h, 0.0));
    EXPECT_TRUE(w.touching(0));
    for (int i = 0; i < 10; ++i) w.step(cmd(0.16, 0.0));
    w.hold(20);  // 2 s holding still in the air
    const ObjectPose p = w.object_pose(0);
    EXPECT_GT(w.object_z_range(0)[0], 0.1) << to_string(shape);
    EXPECT_LT(std::hypot(p.pos[0] - o.pos[0], p.pos[1] - o.pos[1]), 0.01);
    EXPECT_LT(std::fabs(p.pos[2] - (0.16 - 0.0)), 0.02);  // still centred between the pads
    // Opening drops it back onto the table.
    w.step(cmd(0.16, 1.0));
    w.hold(15);
    EXPECT_LT(w.object_z_range(0)[0], 0.005);
  }
}

TEST(SimWorld, HumanGraspAssistCarriesAndReleases) {
  SceneSpec spec = sample_scene(Embodiment::kHuman, {}, 2);
  ObjectSpec o;
  o.shape = Shape::kBox;
  o.size = {0.025, 0.025, 0.02};
  o.mass = 0.1;
  o.pos = {0.0, 0.05, 0.0};
  spec.objects = {o};
  World w(spec);
  w.hold(3);
  const double z = 0.04 + 0.011 - 0.002;  // palm resting on the box top
  const double y = 0.05 - 0.012;
  for (int i = 0; i < 10; ++i) w.step({0.0, y, z + 0.06, 0.0, 0.0, 0.05});
  for (int i = 0; i < 5; ++i) w.step({0.0, y, z, 0.0, 0.0, 0.05});
  EXPECT_EQ(w.grasped_object(), -1);
  for (int i = 0; i < 5; ++i) w.step({0.0, y, z, 0.0, 0.0, 0.95});
  EXPECT_EQ(w.grasped_object(), 0);
  for (int i = 0; i < 10; ++i) w.step({0.1, y, z + 0.1, 0.0, 0.0, 0.95});
  EXPECT_GT(w.object_z_range(0)[0], 0.08);
  EXPECT_NEAR(w.object_pose(0).pos[0], 0.1, 0.01);
  for (int i = 0; i < 3; ++i) w.step({0.1, y, z + 0.1, 0.0, 0.0, 0.1});
  EXPECT_EQ(w.grasped_object(), -1);
  w.hold(15);
  EXPECT_NEAR(w.object_z_range(0)[0], 0.0, 0.004);  // fell back to the table
}

TEST(SimWorld, SteppingIsDeterministic) {
  auto run = [] {
    World w(sample_scene(Embodiment::kHuman, {}, 11));
    auto c = make_human_controller(w, {}, 11);
    for (int t = 0; t < 40; ++t) w.step(c->act(w, t));
    const mjData* d = w.data();
    return std::vector<double>(d->qpos, d->qpos + w.model()->nq);
  };
  const std::vector<double> a = run(), b = run();
  ASSERT_EQ(a.size(), b.size());
  EXPECT_EQ(std::memcmp(a.data(), b.data(), a.size() * sizeof(double)), 0);
}

TEST(SimWorld, ResetRestoresTheInitialState) {
  World w(sample_scene(Embodiment::kRobot, {}, 4));
  const std::vector<ObjectPose> start = w.object_poses();
  const std::vector<double> s0 = w.state();
  for (int i = 0; i < 10; ++i) w.step(robot_command({0.0, 0.0, 0.05}, 0.0));
  w.reset();
  EXPECT_EQ(w.sim_time(), 0.0);
  EXPECT_EQ(w.control_steps(), 0);
  EXPECT_EQ(w.state(), s0);
  for (int i = 0; i < w.num_objects(); ++i) EXPECT_EQ(w.object_pose(i).pos, start[i].pos);
}

TEST(SimWorld, SetObjectPoseAndZRange) {
  SceneSpec spec = sample_scene(Embodiment::kRobot, {}, 0);
  ObjectSpec o;
  o.size = {0.02, 0.03, 0.01};
  spec.objects = {o};
  World w(spec);
  w.set_object_pose(0, {0.05, 0.0, 0.2});
  EXPECT_NEAR(w.object_z_range(0)[0], 0.19, 1e-9);
  EXPECT_NEAR(w.object_z_range(0)[1], 0.21, 1e-9);
  // Rotated 90 degrees about x: the 3 cm half-extent now points up.
  const double s = std::sqrt(0.5);
  w.set_object_pose(0, {0.05, 0.0, 0.2}, {s, s, 0, 0});
  EXPECT_NEAR(w.object_z_range(0)[1], 0.23, 1e-9);
  EXPECT_THROW(w.object_pose(3), Error);
}

TEST(SimWorld, RejectsBadCommands) {
  World w(sample_scene(Embodiment::kRobot, {}, 0));
  EXPECT_EQ(w.action_dim(), 6);
  EXPECT_THROW(w.step({0.0, 0.0}), Error);
  EXPECT_THROW(w.step({0, 0, 0, 0, NAN, 0}), Error);
  // Out-of-range values are clamped, not rejected.
  EXPECT_NO_THROW(w.step({10, -10, 10, -10, 10, 5}));
  EXPECT_LE(w.last_command()[5], 1.0);
}

}  // namespace
}  // namespace dojo::sim
