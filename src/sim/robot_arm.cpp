#include "sim/robot_arm.h"

#include <algorithm>
#include <cmath>

namespace dojo::sim::arm {
namespace {

double wrap_angle(double a) {
  while (a > M_PI) a -= 2.0 * M_PI;
  while (a < -M_PI) a += 2.0 * M_PI;
  return a;
}

double base_yaw_for(const Point& p) { return std::atan2(-(p[0] - kBaseX), p[1] - kBaseY); }

}  // namespace

Point forward_grasp_point(const Joints& q) {
  const double a1 = q[1], a2 = q[1] + q[2], a3 = q[1] + q[2] + q[3];
  // In the arm's vertical plane: r is the horizontal distance along the forward direction.
  const double r = kUpperLen * std::sin(a1) + kForeLen * std::sin(a2) + kGripLen * std::sin(a3);
  const double z = kShoulderZ + kUpperLen * std::cos(a1) + kForeLen * std::cos(a2) + kGripLen * std::cos(a3);
  return {kBaseX - r * std::sin(q[0]), kBaseY + r * std::cos(q[0]), z};
}

bool solve_topdown_ik(const Point& p, double closing_yaw, Joints* q) {
  const double dx = p[0] - kBaseX, dy = p[1] - kBaseY;
  const double r = std::hypot(dx, dy);
  const double q0 = base_yaw_for(p);
  // Gripper points down, so the wrist axis sits kGripLen straight above the grasp point.
  const double wr = r, wz = p[2] + kGripLen - kShoulderZ;
  double d = std::hypot(wr, wz);
  bool ok = true;
  const double dmax = kUpperLen + kForeLen - 1e-6;
  const double dmin = std::fabs(kUpperLen - kForeLen) + 1e-6;
  if (d > dmax) {
    ok = false;
    d = dmax;
  } else if (d < dmin) {
    ok = false;
    d = dmin;
  }
  const double c2 = std::clamp(
      (d * d - kUpperLen * kUpperLen - kForeLen * kForeLen) / (2.0 * kUpperLen * kForeLen), -1.0, 1.0);
  const double q2 = std::acos(c2);  // positive: elbow above the shoulder-wrist line
  // Angles are measured from vertical toward the forward direction.
  const double q1 =
      std::atan2(wr, wz) - std::atan2(kForeLen * std::sin(q2), kUpperLen + kForeLen * std::cos(q2));
  const double q3 = M_PI - q1 - q2;
  const double q4 = wrap_angle(q0 - closing_yaw);
  *q = {q0, q1, q2, q3, q4};
  for (int i = 0; i < kNumArmJoints; ++i) {
    if ((*q)[i] < kJointLimits[i].lo || (*q)[i] > kJointLimits[i].hi) ok = false;
    (*q)[i] = std::clamp((*q)[i], kJointLimits[i].lo, kJointLimits[i].hi);
  }
  return ok;
}

double neutral_closing_yaw(const Point& p) { return base_yaw_for(p); }

double box_closing_yaw(const Point& p, double box_yaw) {
  const double neutral = base_yaw_for(p);
  // Faces repeat every 90 degrees; pick the face pair whose normal is nearest to neutral.
  const double k = std::round((neutral - box_yaw) / (M_PI / 2.0));
  return box_yaw + k * (M_PI / 2.0);
}

Joints home_joints() {
  Joints q{};
  solve_topdown_ik({0.1, -0.1, 0.14}, 0.0, &q);
  q[4] = 0.0;
  return q;
}

}  // namespace dojo::sim::arm
