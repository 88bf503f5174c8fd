// Scripting helpers shared by the human skills and the robot policies (see skill_script.h).
#include "sim/skill_script.h"

#include <algorithm>
#include <array>
#include <cmath>

#include "sim/robot_arm.h"

namespace dojo::sim {
namespace {

double yaw_of(const std::array<double, 4>& q) {
  return std::atan2(2.0 * (q[0] * q[3] + q[1] * q[2]), 1.0 - 2.0 * (q[2] * q[2] + q[3] * q[3]));
}

}  // namespace

ObjInfo object_info(const World& w, int i) {
  ObjInfo o;
  o.index = i;
  const ObjectPose p = w.object_pose(i);
  o.pos = p.pos;
  o.yaw = yaw_of(p.quat);
  const auto z = w.object_z_range(i);
  o.bottom = z[0];
  o.top = z[1];
  o.radius = object_footprint_radius(w.spec().objects[i]);
  o.name = object_description(w.spec().objects[i]);
  o.shape = w.spec().objects[i].shape;
  return o;
}

std::string direction_words(double dx, double dy) {
  const double a = std::atan2(dy, dx) * 180.0 / M_PI;  // 0 = right, 90 = away from the camera
  if (a > -30 && a <= 30) return "to the right";
  if (a > 30 && a <= 60) return "forward and to the right";
  if (a > 60 && a <= 120) return "forward";
  if (a > 120 && a <= 150) return "forward and to the left";
  if (a > 150 || a <= -150) return "to the left";
  if (a > -150 && a <= -120) return "back and to the left";
  if (a > -120 && a <= -60) return "toward me";
  return "back and to the right";
}

double bin_grasp_height(const ObjInfo& o) {
  const double palm_gap = arm::kGripLen - arm::kFingerStart;  // grasp point -> palm underside
  return std::max({0.018, std::min(o.pos[2], o.top - 0.025), o.top - palm_gap + 0.005});
}

double bin_grasp_roll(const ObjInfo& o, double x, double y) {
  if (o.shape != Shape::kBox && o.shape != Shape::kDumbbell) return 0.0;
  const arm::Point p{x, y, 0.0};
  const double psi = arm::box_closing_yaw(p, o.yaw + (o.shape == Shape::kDumbbell ? M_PI / 2 : 0.0));
  double roll = arm::neutral_closing_yaw(p) - psi;
  while (roll > M_PI) roll -= 2.0 * M_PI;
  while (roll < -M_PI) roll += 2.0 * M_PI;
  return roll;
}

bool on_table(double x, double y) { return std::fabs(x) < 0.4 && y > -0.28 && y < 0.34; }

}  // namespace dojo::sim
