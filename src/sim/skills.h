// Scripted behaviour for DojoSim: human skills and robot policies. Every controller is a pure
// function of (world state, its seed), so an episode replays exactly.
//
// Human skills are keyframe scripts over the hand command [x, y, z, yaw, pitch, curl] (see
// world.h), planned from the current object poses when the skill starts and interpolated with
// minimum-jerk profiles. Speed, approach direction, heights, amplitudes and repetitions vary per
// episode. With `chain`, a new skill is planned whenever one finishes, so any episode length
// stays busy.
//
// Robot policies plan Cartesian keyframes for the grasp point (top-down gripper), turned into
// joint targets by the analytic IK in robot_arm.h. The bin policy is closed-loop per attempt:
// each attempt targets the nearest object not yet in the bin, using its current pose. Quality
// knobs degrade it in controlled ways (PolicyQuality). Counterfactual behaviours (pat,
// reach-and-miss, push, random smooth joint motion) reuse the same machinery; idle holds still.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "sim/world.h"

namespace dojo::sim {

class Controller {
 public:
  virtual ~Controller() = default;
  // The command issued after observing the world at control step `step` (0, 1, 2, ... in
  // order); it is the target the embodiment reaches by the end of that step.
  virtual std::vector<double> act(const World& world, int step) = 0;
  // Natural-language instruction for what the controller did so far ("push the red cube to the
  // left, then pat the blue ball").
  virtual std::string task_text() const = 0;
  // Behaviour names and sampled parameters, for episode metadata.
  virtual nlohmann::json describe() const = 0;
};

// ------------------------------------------------------------------------------------------------
// Human

enum class HumanSkill { kPush, kPoke, kPat, kSweep, kPickPlace, kStack, kTopple, kReach, kLiftDrop };
constexpr int kNumHumanSkills = 9;
const char* to_string(HumanSkill skill);
HumanSkill parse_human_skill(const std::string& name);  // throws dojo::UsageError
std::vector<HumanSkill> all_human_skills();

struct HumanSkillOptions {
  std::vector<HumanSkill> skills;  // each skill is drawn uniformly from these; empty = all
  bool chain = true;               // plan another skill when one finishes
  int target_object = -1;          // the first skill's object; -1 = random
};

// Throws dojo::Error unless the world is a human scene.
std::unique_ptr<Controller> make_human_controller(const World& world, const HumanSkillOptions& options,
                                                  uint64_t seed);

// ------------------------------------------------------------------------------------------------
// Robot

// Ways a scripted bin policy goes wrong, each drawn independently per pick attempt.
struct PolicyQuality {
  double noise_std = 0.0;           // std of smooth AR(1) noise added to joint targets, rad
  int delay_steps = 0;              // commands reach the robot this many control steps late
  double miss_prob = 0.0;           // grasp 4-6 cm beside the object (wrong grasp target)
  double wrong_target_prob = 0.0;   // place on the table instead of in the bin
  double wrong_object_prob = 0.0;   // go for a random object, even one already in the bin
  double early_release_prob = 0.0;  // open the gripper during transport
  double speed = 1.0;               // motion speed multiplier (> 1 is faster)

  // Named presets: "expert", "good", "medium", "poor". Throws dojo::UsageError otherwise.
  static PolicyQuality preset(const std::string& name);
  // A preset name or an object of the knobs above (absent ones keep their defaults); unknown knobs
  // and out-of-range values throw dojo::Error naming `where`.
  static PolicyQuality from_json(const nlohmann::json& j, const std::string& where);
  nlohmann::json to_json() const;
};

enum class RobotBehavior {
  kBinPick,       // put the objects in the bin (the task)
  kPat,           // pat the top of an object with the closed gripper
  kReachMiss,     // reach for an object, grasp beside it, lift nothing
  kPush,          // push an object sideways with the closed gripper
  kRandomMotion,  // random smooth joint-space motion
  kTeleopPlay,    // an operator at the keyboard: one or two joints at a key's constant rate (quality ignored)
  kIdle,          // hold the settled start command: a policy that does nothing (quality ignored)
};
const char* to_string(RobotBehavior behavior);
RobotBehavior parse_robot_behavior(const std::string& name);  // throws dojo::UsageError

struct RobotPolicyOptions {
  RobotBehavior behavior = RobotBehavior::kBinPick;
  PolicyQuality quality;   // bin policy only (noise and delay also apply to the others)
  int target_object = -1;  // counterfactual behaviours: object to act on; -1 = random
};

// Throws dojo::Error unless the world is a robot scene (and, for kBinPick, has a bin).
std::unique_ptr<Controller> make_robot_controller(const World& world, const RobotPolicyOptions& options,
                                                  uint64_t seed);

}  // namespace dojo::sim
