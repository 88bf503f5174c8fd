// The belief-driven bin controller: the attempt of robot_policies.cpp's bin policy (hover,
// descend, close, lift, carry, lower, release, rise), planned from a BinBelief.
#include "sim/bin_belief.h"

#include <algorithm>
#include <cmath>

#include "core/error.h"
#include "sim/robot_arm.h"
#include "sim/skill_script.h"
#include "sim/world.h"

namespace dojo::sim {
namespace {

// The bin's inner half-extent in DojoSim's robot scenes (scene.h BinSpec), less a margin: a centre
// read within it is in the bin.
constexpr double kBinInside = 0.075 - 0.01;

}  // namespace

std::vector<double> BinBelief::to_values() const {
  return {object_x, object_y, grasp_z, drop_offset, std::cos(2 * roll), std::sin(2 * roll), bin_x, bin_y};
}

BinBelief BinBelief::from_values(const std::vector<double>& v) {
  DOJO_CHECK(static_cast<int>(v.size()) == kValues,
             "bin belief: expected " + std::to_string(kValues) + " values, got " + std::to_string(v.size()));
  BinBelief b;
  b.object_x = v[0];
  b.object_y = v[1];
  b.grasp_z = v[2];
  b.drop_offset = v[3];
  b.roll = 0.5 * std::atan2(v[5], v[4]);
  b.bin_x = v[6];
  b.bin_y = v[7];
  return b;
}

bool BinBelief::object_in_bin() const {
  return std::fabs(object_x - bin_x) < kBinInside && std::fabs(object_y - bin_y) < kBinInside;
}

BinBelief true_bin_belief(const World& world) {
  DOJO_CHECK(world.num_objects() > 0 && world.spec().bin.enabled,
             "bin belief: the scene needs an object and a bin");
  const ObjInfo o = object_info(world, 0);
  BinBelief b;
  b.object_x = o.pos[0];
  b.object_y = o.pos[1];
  b.grasp_z = bin_grasp_height(o);
  b.drop_offset = b.grasp_z - o.bottom;
  b.roll = bin_grasp_roll(o, o.pos[0], o.pos[1]);
  b.bin_x = world.spec().bin.center[0];
  b.bin_y = world.spec().bin.center[1];
  return b;
}

BeliefBinController::BeliefBinController(const BeliefControllerOptions& options)
    : options_(options),
      rng_(options.seed),
      noise_(arm::kNumArmJoints, 0.0),
      script_(std::make_unique<Script>()) {
  DOJO_CHECK(options_.start_command.size() == static_cast<size_t>(arm::kActionDim),
             "belief controller: the start command needs " + std::to_string(arm::kActionDim) + " values");
  DOJO_CHECK(options_.control_dt > 0 && options_.speed > 0 && options_.max_attempts > 0,
             "belief controller: control_dt, speed and max_attempts must be positive");
  const auto& c = options_.start_command;
  const arm::Point p = arm::forward_grasp_point({c[0], c[1], c[2], c[3], c[4]});
  home_ = {p[0], p[1], p[2], c[4], c[5]};
}

BeliefBinController::~BeliefBinController() = default;

bool BeliefBinController::plans_at(int step) const {
  return !script_->started() || script_->done(step * options_.control_dt);
}

void BeliefBinController::timed(const std::vector<double>& pose, double seconds) {
  script_->add(pose, seconds / options_.speed);
}

void BeliefBinController::move(const std::vector<double>& pose) {
  const auto& from = script_->end();
  const double dist = std::hypot(pose[0] - from[0], pose[1] - from[1], pose[2] - from[2]);
  script_->add(pose, std::clamp(dist / (0.3 * options_.speed), 0.6, 2.0));
}

void BeliefBinController::plan(const BinBelief& b, double now) {
  if (!finished_ && (b.object_in_bin() || attempts_ >= options_.max_attempts)) {
    finished_ = true;
    std::vector<double> up = script_->end();
    up[2] = std::max(up[2], 0.18);
    timed(up, 0.4);
    move(home_);
    return;
  }
  if (finished_) {
    script_->wait(1.0);
    return;
  }
  ++attempts_;
  const auto cart = [](double x, double y, double z, double roll, double grip) {
    return std::vector<double>{x, y, z, roll, grip};
  };
  const double gz = b.grasp_z, roll = b.roll;
  move(cart(b.object_x, b.object_y, gz + kBinHoverZ, roll, 1.0));
  timed(cart(b.object_x, b.object_y, gz, roll, 1.0), 0.8);
  timed(cart(b.object_x, b.object_y, gz, roll, 0.0), 0.5);
  timed(cart(b.object_x, b.object_y, kBinCarryZ, roll, 0.0), 0.7);
  // The object's bottom ends 1.6 cm above the bin floor before release, as the bin policy's.
  const double drop_z = 0.016 + b.drop_offset;
  move(cart(b.bin_x, b.bin_y, kBinCarryZ, roll, 0.0));
  timed(cart(b.bin_x, b.bin_y, drop_z, roll, 0.0), 0.5);
  timed(cart(b.bin_x, b.bin_y, drop_z, roll, 1.0), 0.4);
  timed(cart(b.bin_x, b.bin_y, 0.18, roll, 1.0), 0.5);
  log_.push_back({{"attempt", attempts_},
                  {"start_step", static_cast<int>(std::lround(now / options_.control_dt))},
                  {"object", {b.object_x, b.object_y}},
                  {"bin", {b.bin_x, b.bin_y}}});
}

std::vector<double> BeliefBinController::act(const BinBelief& belief, int step) {
  const double dt = options_.control_dt, now = step * dt;
  if (!script_->started()) {
    script_->start(home_, now);
    plan(belief, now);
  } else if (script_->done(now)) {
    script_->start(script_->end(), now);
    plan(belief, now);
  }
  const auto target = script_->eval(now + dt);
  arm::Joints q{};
  arm::solve_topdown_ik({target[0], target[1], target[2]}, 0.0, &q);
  std::vector<double> command(arm::kActionDim);
  for (int j = 0; j < 4; ++j) command[j] = q[j];
  command[4] = target[3];
  command[5] = target[4];
  if (options_.noise_std > 0) {
    const double a = 0.8;  // as the bin policy's noise: drifting over a few steps
    for (int j = 0; j < arm::kNumArmJoints; ++j) {
      noise_[j] = a * noise_[j] + std::sqrt(1 - a * a) * rng_.normal(0.0, options_.noise_std);
      command[j] += noise_[j];
    }
  }
  for (int j = 0; j < arm::kNumArmJoints; ++j)
    command[j] = std::clamp(command[j], arm::kJointLimits[j].lo, arm::kJointLimits[j].hi);
  command[5] = std::clamp(command[5], 0.0, 1.0);
  return command;
}

nlohmann::json BeliefBinController::describe() const {
  return {
      {"controller", "belief_bin_policy"},     {"speed", options_.speed}, {"noise_std", options_.noise_std},
      {"max_attempts", options_.max_attempts}, {"finished", finished_},   {"attempts", log_}};
}

}  // namespace dojo::sim
