// Robot policies for DojoSim: the RobotController (the scripted bin-picking policy and the
// counterfactual behaviours), the PolicyQuality presets and the robot behaviour names.
#include "sim/skills.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <deque>
#include <set>

#include "core/error.h"
#include "core/json_file.h"
#include "sim/rng.h"
#include "sim/robot_arm.h"
#include "sim/skill_script.h"
#include "sim/task.h"

namespace dojo::sim {
namespace {

constexpr double kCarryZ = kBinCarryZ;
constexpr double kHoverZ = kBinHoverZ;
constexpr double kTipBelow = arm::kGripLen - arm::kFingerStart - arm::kFingerLen;  // negative

class RobotController : public Controller {
 public:
  RobotController(const World& world, const RobotPolicyOptions& options, uint64_t seed)
      : options_(options), rng_(seed), attempts_(world.num_objects(), 0) {
    const std::vector<double>& c = world.initial_command();
    home_joints_ = {c[0], c[1], c[2], c[3], c[4]};
    const arm::Point p = arm::forward_grasp_point(home_joints_);
    home_ = {p[0], p[1], p[2], c[4], c[5]};
    noise_.assign(arm::kNumArmJoints, 0.0);
    for (int i = 0; i < options_.quality.delay_steps; ++i) queue_.push_back(c);
    log_ = nlohmann::json::array();
    if (options_.behavior == RobotBehavior::kBinPick) {
      DOJO_CHECK(world.spec().bin.enabled, "robot bin policy: the scene has no bin");
    }
  }

  std::vector<double> act(const World& world, int step) override {
    const double dt = world.control_dt();
    const double now = step * dt;
    if (!script_.started()) {
      script_.start(home_, now);
      joint_mode_ = false;
      plan(world, now);
    } else if (script_.done(now)) {
      script_.start(script_.end(), now);
      plan(world, now);
    }
    const Pose target = script_.eval(now + dt);
    std::vector<double> command(arm::kActionDim);
    if (joint_mode_) {
      command = target;
    } else {
      arm::Joints q{};
      arm::solve_topdown_ik({target[0], target[1], target[2]}, 0.0, &q);
      for (int j = 0; j < 4; ++j) command[j] = q[j];
      command[4] = std::clamp(target[3], arm::kJointLimits[4].lo, arm::kJointLimits[4].hi);
      command[5] = target[4];
    }
    const PolicyQuality& quality = options_.quality;
    if (quality.noise_std > 0) {
      const double a = 0.8;
      for (int j = 0; j < arm::kNumArmJoints; ++j) {
        noise_[j] = a * noise_[j] + std::sqrt(1 - a * a) * rng_.normal(0.0, quality.noise_std);
        command[j] += noise_[j];
      }
    }
    for (int j = 0; j < arm::kNumArmJoints; ++j) {
      command[j] = std::clamp(command[j], arm::kJointLimits[j].lo, arm::kJointLimits[j].hi);
    }
    command[5] = std::clamp(command[5], 0.0, 1.0);
    if (quality.delay_steps > 0) {
      queue_.push_back(command);
      command = queue_.front();
      queue_.pop_front();
    }
    return command;
  }

  std::string task_text() const override { return text_; }

  nlohmann::json describe() const override {
    return {{"controller", "robot_policy"},
            {"behavior", to_string(options_.behavior)},
            {"quality", options_.quality.to_json()},
            {"attempts", log_}};
  }

 private:
  // Cartesian pose: [x, y, z, wrist_roll, gripper].
  static Pose cart(double x, double y, double z, double roll, double grip) { return {x, y, z, roll, grip}; }
  double s() const { return options_.quality.speed; }
  void timed(const Pose& p, double seconds) { script_.add(p, seconds / s()); }
  void move(const Pose& p, double base_speed = 0.3) {
    const Pose& from = script_.end();
    const double dist =
        std::sqrt(std::pow(p[0] - from[0], 2) + std::pow(p[1] - from[1], 2) + std::pow(p[2] - from[2], 2));
    script_.add(p, std::clamp(dist / (base_speed * s()), 0.6, 2.0));
  }
  void go_home() {
    Pose h = home_;
    h[3] = script_.end()[3];
    Pose up = script_.end();
    up[2] = std::max(up[2], 0.18);
    timed(up, 0.4);
    move(h);
    h[3] = home_[3];
    timed(h, 0.3);
  }

  void plan(const World& w, double now) {
    switch (options_.behavior) {
      case RobotBehavior::kBinPick:
        plan_bin_attempt(w, now);
        break;
      case RobotBehavior::kPat:
      case RobotBehavior::kReachMiss:
      case RobotBehavior::kPush:
        if (!counterfactual_done_) {
          plan_counterfactual(w);
          counterfactual_done_ = true;
        } else {
          script_.wait(1.0);
        }
        break;
      case RobotBehavior::kRandomMotion:
        plan_random(w, now);
        break;
      case RobotBehavior::kTeleopPlay:  // made a TeleopPlayController instead; kept for a complete switch
      case RobotBehavior::kIdle:        // made a HoldController instead; kept for a complete switch
        script_.wait(1.0);
        break;
    }
  }

  int pick_target(const World& w) {
    const int n = w.num_objects();
    if (options_.target_object >= 0 && options_.target_object < n) return options_.target_object;
    return n > 0 ? rng_.randint(0, n - 1) : -1;
  }

  void plan_bin_attempt(const World& w, double now) {
    const PolicyQuality& q = options_.quality;
    const int n = w.num_objects();
    if (text_.empty()) {
      text_ = "put the objects in the bin";
      if (n > 0 && n <= 3) {
        text_ = "put the ";
        for (int i = 0; i < n; ++i) {
          text_ +=
              (i == 0 ? "" : (i + 1 == n ? " and the " : ", the ")) + object_description(w.spec().objects[i]);
        }
        text_ += " in the bin";
      }
    }
    if (finished_) {
      script_.wait(1.0);
      return;
    }
    // Nearest object still outside the bin (and still on the table) from the gripper.
    const Vec3 g = w.grasp_point();
    int target = -1;
    double best = 1e9;
    for (int i = 0; i < n; ++i) {
      const ObjInfo o = object_info(w, i);
      if (object_in_bin(w, i) || attempts_[i] >= 3 || o.bottom < -0.02 || !on_table(o.pos[0], o.pos[1]))
        continue;
      const double d = std::hypot(o.pos[0] - g[0], o.pos[1] - g[1]);
      if (d < best) {
        best = d;
        target = i;
      }
    }
    const bool wrong_object = n > 0 && rng_.bernoulli(q.wrong_object_prob);
    if (wrong_object) target = rng_.randint(0, n - 1);
    if (target < 0) {
      finished_ = true;
      go_home();
      return;
    }
    ++attempts_[target];
    const ObjInfo o = object_info(w, target);
    double gx = o.pos[0], gy = o.pos[1];
    const bool miss = rng_.bernoulli(q.miss_prob);
    if (miss) {
      const double a = rng_.uniform(-M_PI, M_PI), d = o.radius + rng_.uniform(0.025, 0.04);
      gx += d * std::cos(a);
      gy += d * std::sin(a);
    }
    const double gz = bin_grasp_height(o);
    const double roll = bin_grasp_roll(o, gx, gy);
    move(cart(gx, gy, gz + kHoverZ, roll, 1.0));
    timed(cart(gx, gy, gz, roll, 1.0), 0.8);
    timed(cart(gx, gy, gz, roll, 0.0), 0.5);
    timed(cart(gx, gy, kCarryZ, roll, 0.0), 0.7);
    double tx = 0, ty = 0;
    free_bin_spot(w, target, o.radius, &tx, &ty);
    const bool wrong_target = rng_.bernoulli(q.wrong_target_prob);
    if (wrong_target) {
      tx = rng_.uniform(-0.15, 0.05);
      ty = rng_.uniform(-0.1, 0.08);
    }
    const bool early = rng_.bernoulli(q.early_release_prob);
    // The object's bottom ends 1.2 cm above the bin floor (or the table) before release.
    const double drop_z = (wrong_target ? 0.0 : 0.004) + 0.012 + (gz - o.bottom);
    if (early) {
      const double f = rng_.uniform(0.2, 0.7);
      const Pose& from = script_.end();
      const double mx = from[0] + f * (tx - from[0]), my = from[1] + f * (ty - from[1]);
      move(cart(mx, my, kCarryZ, roll, 0.0));
      timed(cart(mx, my, kCarryZ, roll, 1.0), 0.3);
      move(cart(tx, ty, kCarryZ, roll, 1.0));
    } else {
      move(cart(tx, ty, kCarryZ, roll, 0.0));
      timed(cart(tx, ty, drop_z, roll, 0.0), 0.5);
      timed(cart(tx, ty, drop_z, roll, 1.0), 0.4);
    }
    timed(cart(tx, ty, 0.18, roll, 1.0), 0.5);
    log_.push_back({{"object", target},
                    {"start_step", static_cast<int>(std::lround(now / w.control_dt()))},
                    {"miss", miss},
                    {"wrong_object", wrong_object},
                    {"wrong_target", wrong_target},
                    {"early_release", early}});
  }

  // The spot in the bin farthest from the objects already in it (among random candidates).
  void free_bin_spot(const World& w, int carried, double radius, double* x, double* y) {
    const BinSpec& bin = w.spec().bin;
    const double mx = std::max(0.0, bin.half_x - radius - 0.015),
                 my = std::max(0.0, bin.half_y - radius - 0.015);
    double best = -1e9;
    for (int k = 0; k < 24; ++k) {
      const double cx = bin.center[0] + rng_.uniform(-mx, mx), cy = bin.center[1] + rng_.uniform(-my, my);
      double clearance = 1.0;
      for (int j = 0; j < w.num_objects(); ++j) {
        if (j == carried || !object_in_bin(w, j)) continue;
        const ObjInfo other = object_info(w, j);
        clearance =
            std::min(clearance, std::hypot(cx - other.pos[0], cy - other.pos[1]) - other.radius - radius);
      }
      // Prefer clearance, then the centre (small tie-break).
      const double score =
          std::min(clearance, 0.03) - 0.1 * std::hypot(cx - bin.center[0], cy - bin.center[1]);
      if (score > best) {
        best = score;
        *x = cx;
        *y = cy;
      }
    }
  }

  void plan_counterfactual(const World& w) {
    const int target = pick_target(w);
    if (target < 0) {
      text_ = "move the arm over the table";
      move(cart(rng_.uniform(-0.1, 0.05), rng_.uniform(-0.05, 0.1), rng_.uniform(0.08, 0.15), 0.0, 1.0));
      go_home();
      return;
    }
    const ObjInfo o = object_info(w, target);
    nlohmann::json entry = {{"object", target}};
    switch (options_.behavior) {
      case RobotBehavior::kPat: {
        text_ = "pat the " + o.name;
        const double touch = o.top - kTipBelow - 0.004;  // fingertips press 4 mm into the top
        const double amp = rng_.uniform(0.04, 0.07);
        move(cart(o.pos[0], o.pos[1], touch + amp + 0.04, 0.0, 0.0));
        const int pats = rng_.randint(2, 4);
        for (int k = 0; k < pats; ++k) {
          timed(cart(o.pos[0], o.pos[1], touch, 0.0, 0.0), rng_.uniform(0.25, 0.35));
          timed(cart(o.pos[0], o.pos[1], touch + amp, 0.0, 0.0), rng_.uniform(0.3, 0.4));
        }
        entry["pats"] = pats;
        break;
      }
      case RobotBehavior::kReachMiss: {
        text_ = "reach for the " + o.name + " and miss";
        const double a = rng_.uniform(-M_PI, M_PI), d = o.radius + rng_.uniform(0.04, 0.07);
        const double gx = o.pos[0] + d * std::cos(a), gy = o.pos[1] + d * std::sin(a);
        const double gz = bin_grasp_height(o);
        move(cart(gx, gy, gz + kHoverZ, 0.0, 1.0));
        timed(cart(gx, gy, gz, 0.0, 1.0), 0.8);
        timed(cart(gx, gy, gz, 0.0, 0.0), 0.5);
        timed(cart(gx, gy, kCarryZ, 0.0, 0.0), 0.7);
        script_.wait(0.3);
        entry["offset"] = {gx - o.pos[0], gy - o.pos[1]};
        break;
      }
      case RobotBehavior::kPush: {
        const double a = rng_.uniform(-M_PI, M_PI);
        const double dx = std::cos(a), dy = std::sin(a);
        text_ = "push the " + o.name + " " + direction_words(dx, dy);
        // Closed fingers are a 2.4 cm block whose pads reach 1.5 cm below the grasp point.
        const double gz = std::max(0.02, o.bottom - kTipBelow + 0.005);
        const double back = o.radius + 0.03;
        const double sx = o.pos[0] - dx * back, sy = o.pos[1] - dy * back;
        double dist = rng_.uniform(0.06, 0.12);
        while (dist > 0.02 && !on_table(o.pos[0] + dx * dist, o.pos[1] + dy * dist)) dist -= 0.01;
        move(cart(sx, sy, gz + 0.08, 0.0, 0.0));
        timed(cart(sx, sy, gz, 0.0, 0.0), 0.6);
        script_.add(cart(sx + dx * (dist + 0.02), sy + dy * (dist + 0.02), gz, 0.0, 0.0),
                    (dist + 0.02) / (0.08 * s()));
        timed(cart(sx + dx * (dist + 0.02), sy + dy * (dist + 0.02), gz + 0.08, 0.0, 0.0), 0.5);
        entry["direction"] = {dx, dy};
        entry["distance"] = dist;
        break;
      }
      default:
        break;
    }
    go_home();
    log_.push_back(entry);
  }

  // Random smooth joint-space motion between poses whose grasp point stays over the workspace
  // (so the arm stays in view), with extra random wrist pitch/roll and gripper changes.
  void plan_random(const World& w, double now) {
    text_ = "move the arm around";
    if (!joint_mode_) {
      joint_mode_ = true;
      script_.start(w.last_command(), now);
    }
    arm::Joints q{};
    arm::solve_topdown_ik({rng_.uniform(-0.2, 0.2), rng_.uniform(-0.12, 0.2), rng_.uniform(0.04, 0.25)}, 0.0,
                          &q);
    q[3] += rng_.uniform(-0.4, 0.3);
    q[4] = rng_.uniform(-1.5, 1.5);
    Pose target(q.begin(), q.end());
    target.push_back(rng_.bernoulli(0.5) ? 1.0 : rng_.uniform(0.0, 1.0));
    script_.add(target, rng_.uniform(0.8, 2.0) / s());
    if (rng_.bernoulli(0.3)) script_.wait(rng_.uniform(0.1, 0.5));
  }

  RobotPolicyOptions options_;
  Rng rng_;
  std::vector<int> attempts_;
  arm::Joints home_joints_{};
  Pose home_;
  Script script_;
  bool joint_mode_ = false;
  bool finished_ = false;
  bool counterfactual_done_ = false;
  std::vector<double> noise_;
  std::deque<std::vector<double>> queue_;
  std::string text_;
  nlohmann::json log_;
};

// The policy that does nothing: every command is the one the arm already holds (after the settle
// steps, the start pose), so the world stays as it is unless something else moves it.
class HoldController : public Controller {
 public:
  std::vector<double> act(const World& world, int) override { return world.last_command(); }
  std::string task_text() const override { return "hold still"; }
  nlohmann::json describe() const override { return {{"behavior", "idle"}}; }
};

// Play as an operator at the teleoperation page's keyboard makes it: one joint (sometimes two)
// driven at the key's constant rate for 0.3-3.5 s, released, now and then sent back to the start
// command (the page's home key). Rates are those of src/serve/pages/dojosim_robot.mapping.json.
// Scripted demonstrations and random_motion move smoothly between poses over the workspace;
// a held key is a ramp on one joint that can swing the arm far from it, which a world model
// streamed under teleoperation must have seen.
class TeleopPlayController : public Controller {
 public:
  TeleopPlayController(const World& world, uint64_t seed)
      : rng_(seed), home_(world.initial_command()), velocity_(arm::kActionDim, 0.0) {}

  std::vector<double> act(const World& world, int) override {
    if (command_.empty()) command_ = world.last_command();
    if (steps_left_ <= 0) draw_segment(world.control_dt());
    --steps_left_;
    for (size_t j = 0; j < command_.size(); ++j) command_[j] += velocity_[j] * world.control_dt();
    for (int j = 0; j < arm::kNumArmJoints; ++j)
      command_[j] = std::clamp(command_[j], arm::kJointLimits[j].lo, arm::kJointLimits[j].hi);
    command_[5] = std::clamp(command_[5], 0.0, 1.0);
    return command_;
  }
  std::string task_text() const override { return "move the arm around"; }
  nlohmann::json describe() const override { return {{"behavior", to_string(RobotBehavior::kTeleopPlay)}}; }

 private:
  static constexpr std::array<double, arm::kActionDim> kKeyRates = {0.8, 0.6, 0.6, 0.8, 1.0, 1.5};

  void draw_segment(double dt) {
    std::fill(velocity_.begin(), velocity_.end(), 0.0);
    const double u = rng_.uniform(0.0, 1.0);
    if (u < 0.15) {  // home: the command jumps back, the arm follows while the keys rest
      command_ = home_;
      steps_left_ = static_cast<int>(rng_.uniform(0.5, 1.5) / dt);
      return;
    }
    if (u < 0.35) {  // keys released
      steps_left_ = static_cast<int>(rng_.uniform(0.2, 1.5) / dt);
      return;
    }
    const int joints = rng_.bernoulli(0.25) ? 2 : 1;
    for (int k = 0; k < joints; ++k) {
      const int dim = rng_.randint(0, arm::kActionDim - 1);
      const double speed = rng_.bernoulli(0.6) ? 1.0 : rng_.uniform(0.3, 1.0);  // a gamepad's partial tilt
      velocity_[dim] = (rng_.bernoulli(0.5) ? 1.0 : -1.0) * speed * kKeyRates[dim];
    }
    steps_left_ = std::max(1, static_cast<int>(rng_.uniform(0.3, 3.5) / dt));
  }

  Rng rng_;
  std::vector<double> home_;
  std::vector<double> command_;
  std::vector<double> velocity_;
  int steps_left_ = 0;
};

}  // namespace

// ================================================================================================

PolicyQuality PolicyQuality::preset(const std::string& name) {
  PolicyQuality q;
  if (name == "expert") return q;
  if (name == "good") {
    q.noise_std = 0.01;
    q.miss_prob = q.wrong_target_prob = q.early_release_prob = 0.05;
    return q;
  }
  if (name == "medium") {
    q.noise_std = 0.025;
    q.delay_steps = 1;
    q.miss_prob = q.wrong_target_prob = q.early_release_prob = 0.15;
    q.wrong_object_prob = 0.05;
    return q;
  }
  if (name == "poor") {
    q.noise_std = 0.06;
    q.delay_steps = 3;
    q.miss_prob = 0.4;
    q.wrong_target_prob = 0.35;
    q.early_release_prob = 0.35;
    q.wrong_object_prob = 0.2;
    return q;
  }
  throw UsageError("unknown policy quality '" + name + "' (expected expert, good, medium or poor)");
}

PolicyQuality PolicyQuality::from_json(const nlohmann::json& j, const std::string& where) {
  if (j.is_string()) return preset(j.get<std::string>());
  DOJO_CHECK(j.is_object(), where + ": 'quality' must be a preset name or an object of knobs");
  PolicyQuality q;
  const JsonFields f(j, where + ".quality");
  int64_t delay = q.delay_steps;
  f.get("noise_std", q.noise_std);
  f.get("delay_steps", delay);
  f.get("miss_prob", q.miss_prob);
  f.get("wrong_target_prob", q.wrong_target_prob);
  f.get("wrong_object_prob", q.wrong_object_prob);
  f.get("early_release_prob", q.early_release_prob);
  f.get("speed", q.speed);
  q.delay_steps = static_cast<int>(delay);
  static const std::set<std::string> kKnown = {
      "noise_std",         "delay_steps",        "miss_prob", "wrong_target_prob",
      "wrong_object_prob", "early_release_prob", "speed"};
  for (const auto& [key, value] : j.items())
    DOJO_CHECK(kKnown.count(key), where + ".quality: unknown knob '" + key + "'");
  for (double p : {q.miss_prob, q.wrong_target_prob, q.wrong_object_prob, q.early_release_prob})
    DOJO_CHECK(p >= 0 && p <= 1, where + ".quality: probabilities must be in [0, 1]");
  DOJO_CHECK(q.noise_std >= 0, where + ".quality: noise_std must be >= 0");
  return q;
}

nlohmann::json PolicyQuality::to_json() const {
  return {{"noise_std", noise_std},
          {"delay_steps", delay_steps},
          {"miss_prob", miss_prob},
          {"wrong_target_prob", wrong_target_prob},
          {"wrong_object_prob", wrong_object_prob},
          {"early_release_prob", early_release_prob},
          {"speed", speed}};
}

const char* to_string(RobotBehavior behavior) {
  switch (behavior) {
    case RobotBehavior::kBinPick:
      return "bin_pick";
    case RobotBehavior::kPat:
      return "pat";
    case RobotBehavior::kReachMiss:
      return "reach_miss";
    case RobotBehavior::kPush:
      return "push";
    case RobotBehavior::kRandomMotion:
      return "random_motion";
    case RobotBehavior::kTeleopPlay:
      return "teleop_play";
    case RobotBehavior::kIdle:
      return "idle";
  }
  return "?";
}

RobotBehavior parse_robot_behavior(const std::string& name) {
  for (int i = 0; i <= static_cast<int>(RobotBehavior::kIdle); ++i) {
    if (name == to_string(static_cast<RobotBehavior>(i))) return static_cast<RobotBehavior>(i);
  }
  throw UsageError("unknown robot behavior '" + name +
                   "' (expected bin_pick, pat, reach_miss, push, random_motion, teleop_play or idle)");
}

std::unique_ptr<Controller> make_robot_controller(const World& world, const RobotPolicyOptions& options,
                                                  uint64_t seed) {
  DOJO_CHECK(world.embodiment() == Embodiment::kRobot, "robot policies need a robot scene");
  DOJO_CHECK(options.quality.speed > 0.1 && options.quality.speed < 10,
             "policy quality: speed must be in (0.1, 10)");
  DOJO_CHECK(options.quality.delay_steps >= 0 && options.quality.delay_steps < 100,
             "policy quality: delay_steps must be in [0, 100)");
  if (options.behavior == RobotBehavior::kIdle) return std::make_unique<HoldController>();
  if (options.behavior == RobotBehavior::kTeleopPlay)
    return std::make_unique<TeleopPlayController>(world, seed);
  return std::make_unique<RobotController>(world, options, seed);
}

}  // namespace dojo::sim
