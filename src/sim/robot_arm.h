// Geometry and kinematics of DojoSim's robot: a 5-DoF arm (base yaw, shoulder pitch, elbow pitch,
// wrist pitch, wrist roll) built from capsules, with a two-finger parallel gripper on slide joints.
// The MJCF generator (scene_mjcf.cpp) and the scripted policies (robot_policies.cpp) both read
// these constants, so the analytic inverse kinematics below matches the simulated arm exactly.
//
// Conventions. Joint angles are radians. With all joints at 0 the arm points straight up; the
// pitch joints tilt the chain toward the arm's forward direction, which at base_yaw = 0 is world
// +y (away from the camera). The "grasp point" is the point between the finger pads where a
// grasped object's centre sits. The gripper command is an opening fraction in [0, 1]:
// 1 = fully open (finger gap 2 * kFingerTravel), 0 = closed.
#pragma once

#include <array>

namespace dojo::sim::arm {

using Joints = std::array<double, 5>;
using Point = std::array<double, 3>;

constexpr int kNumArmJoints = 5;
constexpr int kActionDim = 6;  // 5 joint targets + gripper opening fraction

// Base of the arm on the table (table top is z = 0), at the right edge of the view, so the arm
// reaches in from the right and its raised elbow does not hide the workspace.
constexpr double kBaseX = 0.34;
constexpr double kBaseY = -0.10;
constexpr double kYawHeight = 0.025;     // base plate thickness; the yaw joint sits on top
constexpr double kShoulderZ = 0.16;      // height of the shoulder pitch axis above the table
constexpr double kUpperLen = 0.30;       // shoulder -> elbow
constexpr double kForeLen = 0.30;        // elbow -> wrist pitch axis
constexpr double kGripLen = 0.105;       // wrist pitch axis -> grasp point
constexpr double kFingerStart = 0.06;    // wrist pitch axis -> finger roots (palm underside)
constexpr double kFingerLen = 0.06;      // finger length (tips 0.015 beyond the grasp point)
constexpr double kFingerTravel = 0.045;  // per-finger opening at command 1

struct Limits {
  double lo, hi;
};
constexpr std::array<Limits, kNumArmJoints> kJointLimits = {{
    {-2.8, 2.8},  // base_yaw
    {-1.2, 2.0},  // shoulder
    {-0.3, 2.8},  // elbow
    {-2.0, 2.6},  // wrist_pitch
    {-3.1, 3.1},  // wrist_roll
}};

// Grasp point in world coordinates for the given joint angles.
Point forward_grasp_point(const Joints& q);

// Top-down grasp IK: joint angles that put the grasp point at `p` with the gripper pointing
// straight down and its closing direction at world angle `closing_yaw` (radians about +z,
// 0 = fingers close along world x). Elbow-up solution. Returns false when `p` is out of reach;
// `q` then holds the closest pose along the same direction (arm stretched), still finite.
bool solve_topdown_ik(const Point& p, double closing_yaw, Joints* q);

// The closing yaw for a box with the given yaw (4-fold symmetric) closest to the arm's neutral
// roll at `p`, so the wrist turns as little as possible.
double box_closing_yaw(const Point& p, double box_yaw);
// The closing yaw with zero wrist roll at `p` (for round objects).
double neutral_closing_yaw(const Point& p);

// Home pose: gripper open above the front of the workspace, clear of the objects.
Joints home_joints();

}  // namespace dojo::sim::arm
