#include "sim/task.h"

#include <cmath>

#include <nlohmann/json.hpp>

#include "core/error.h"

namespace dojo::sim {
namespace {

// World-frame z axis of a body with quaternion q (w, x, y, z): third column of its rotation.
Vec3 up_axis(const std::array<double, 4>& q) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  return {2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)};
}

double norm3(const Vec3& v) { return std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

}  // namespace

bool object_in_bin(const World& world, int index) {
  const BinSpec& bin = world.spec().bin;
  if (!bin.enabled) return false;
  const ObjectPose p = world.object_pose(index);
  if (std::fabs(p.pos[0] - bin.center[0]) > bin.half_x || std::fabs(p.pos[1] - bin.center[1]) > bin.half_y) {
    return false;
  }
  // Resting on the floor of the bin, or on another object in it; not hovering above it.
  return world.object_z_range(index)[0] < bin.center[2] + bin.wall_height + kBinStackAllowance;
}

bool object_resting(const World& world, int index) {
  const ObjectPose p = world.object_pose(index);
  return norm3(p.linvel) < kRestLinearSpeed && norm3(p.angvel) < kRestAngularSpeed;
}

double bin_success(const World& world) {
  DOJO_CHECK(world.spec().bin.enabled, "bin_success: the scene has no bin");
  const int n = world.num_objects();
  if (n == 0) return 0.0;
  int placed = 0;
  for (int i = 0; i < n; ++i) {
    if (object_in_bin(world, i) && object_resting(world, i) && !world.touching(i)) ++placed;
  }
  return static_cast<double>(placed) / n;
}

double object_displacement(const ObjectPose& initial, const ObjectPose& now) {
  return std::hypot(now.pos[0] - initial.pos[0], now.pos[1] - initial.pos[1]);
}

double object_tilt_degrees(const ObjectPose& initial, const ObjectPose& now) {
  const Vec3 a = up_axis(initial.quat), b = up_axis(now.quat);
  const double c = std::clamp(a[0] * b[0] + a[1] * b[1] + a[2] * b[2], -1.0, 1.0);
  return std::acos(c) * 180.0 / M_PI;
}

nlohmann::json object_outcomes(const World& world, const std::vector<ObjectPose>& initial) {
  DOJO_CHECK(static_cast<int>(initial.size()) == world.num_objects(),
             "object_outcomes: initial pose count mismatch");
  nlohmann::json out = nlohmann::json::array();
  for (int i = 0; i < world.num_objects(); ++i) {
    const ObjectPose now = world.object_pose(i);
    const double tilt = object_tilt_degrees(initial[i], now);
    const auto z = world.object_z_range(i);
    out.push_back(
        {{"displacement", object_displacement(initial[i], now)},
         {"tilt_deg", tilt},
         {"toppled", tilt > 45.0},
         {"lifted", z[0] > 0.02 + (object_in_bin(world, i) ? 0.004 : 0.0)},
         {"in_bin", object_in_bin(world, i)},
         {"on_table", z[0] > -0.01 && std::fabs(now.pos[0]) < 0.55 && std::fabs(now.pos[1]) < 0.42}});
  }
  return out;
}

int bin_task_stage(const World& world) {
  DOJO_CHECK(world.spec().bin.enabled && world.num_objects() > 0,
             "bin task stage: the scene needs a bin and an object");
  if (bin_success(world) > 0.5) return 4;
  const auto z = world.object_z_range(0);
  const ObjectPose pose = world.object_pose(0);
  const bool lifted = z[0] > 0.015 && world.touching(0);  // held, also while lowered into the bin
  const BinSpec& bin = world.spec().bin;
  const bool over_bin = std::fabs(pose.pos[0] - bin.center[0]) < bin.half_x &&
                        std::fabs(pose.pos[1] - bin.center[1]) < bin.half_y;
  if (lifted && over_bin) return 3;
  if (lifted) return 2;
  const Vec3 g = world.grasp_point();
  const double d = std::sqrt(std::pow(g[0] - pose.pos[0], 2) + std::pow(g[1] - pose.pos[1], 2) +
                             std::pow(g[2] - pose.pos[2], 2));
  return d < 0.04 ? 1 : 0;
}

}  // namespace dojo::sim
