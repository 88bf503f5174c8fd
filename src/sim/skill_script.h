// Internal to src/sim: the scripting machinery that the human skills (human_skills.cpp) and the
// robot policies (robot_policies.cpp) share: minimum-jerk keyframe scripts and what a script
// needs to know about an object right now.
#pragma once

#include <algorithm>
#include <string>
#include <vector>

#include "sim/world.h"

namespace dojo::sim {

using Pose = std::vector<double>;

// Minimum-jerk time scaling: zero velocity and acceleration at both ends.
inline double min_jerk(double s) {
  s = std::clamp(s, 0.0, 1.0);
  return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s);
}

// Keyframes in some pose space, interpolated with minimum jerk between consecutive keys.
class Script {
 public:
  void start(const Pose& pose, double t0) {
    start_ = pose;
    keys_.clear();
    t0_ = t0;
    total_ = 0.0;
  }
  void add(const Pose& pose, double duration) {
    duration = std::max(duration, 0.05);
    keys_.push_back({pose, duration});
    total_ += duration;
  }
  void wait(double duration) { add(end(), duration); }
  const Pose& end() const { return keys_.empty() ? start_ : keys_.back().pose; }
  bool started() const { return !start_.empty(); }
  bool done(double t) const { return t >= t0_ + total_ - 1e-9; }
  Pose eval(double t) const {
    double local = t - t0_;
    Pose from = start_;
    for (const Key& k : keys_) {
      if (local <= k.duration) {
        const double s = min_jerk(local / k.duration);
        Pose out(from.size());
        for (size_t i = 0; i < from.size(); ++i) out[i] = from[i] + s * (k.pose[i] - from[i]);
        return out;
      }
      local -= k.duration;
      from = k.pose;
    }
    return end();
  }

 private:
  struct Key {
    Pose pose;
    double duration;
  };
  Pose start_;
  std::vector<Key> keys_;
  double t0_ = 0.0;
  double total_ = 0.0;
};

// What the scripts need to know about an object right now.
struct ObjInfo {
  int index = -1;
  Vec3 pos{};
  double yaw = 0.0;
  double bottom = 0.0, top = 0.0;
  double radius = 0.0;  // footprint radius (upright)
  std::string name;
  Shape shape = Shape::kBox;
};

ObjInfo object_info(const World& w, int i);

// The bin policy's grasp (robot_policies.cpp; the belief controller of bin_belief.h plans the
// same attempt from a reading of the frame). Heights of the grasp point, metres above the table.
constexpr double kBinCarryZ = 0.16;  // while carrying
constexpr double kBinHoverZ = 0.10;  // approach height above the grasp height
// The grasp point's height that takes `o`: its centre, but high enough that the fingertips clear
// the table and low enough that the palm clears its top.
double bin_grasp_height(const ObjInfo& o);
// The wrist roll that aligns the fingers with a box's faces when grasping at (x, y) (0 for round
// objects).
double bin_grasp_roll(const ObjInfo& o, double x, double y);

// "to the right", "forward and to the left", "toward me", ... for a horizontal direction.
std::string direction_words(double dx, double dy);

bool on_table(double x, double y);

}  // namespace dojo::sim
