// One DojoSim episode: build the world, settle it, run a controller for T control steps at
// 10 Hz and record what a dataset needs.
//
// Alignment (LeRobot convention): T frames, T states, T actions; frame[t] and state[t] are
// observed before action[t] is issued, and action[t] is the command the world executes during
// step t. Frame 0 is the scene after `settle_steps` steps holding the rest pose.
//
// Human episodes have NO actions and NO states (human video carries no action labels); their
// hidden_motion rows are the hand commands [x, y, z, yaw, pitch, curl]. hidden_motion exists only
// to measure how well latent actions capture motion and must never be used for training.
// Robot episodes record actions (joint targets + gripper), states (measured joints + gripper)
// and, as hidden_motion, the grasp-point pose [x, y, z, closing_yaw, gripper].
#pragma once

#include <cstdint>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "sim/scene.h"
#include "sim/skills.h"

namespace dojo::sim {

class Renderer;

enum class ControllerKind {
  kHumanSkill,   // scripted human skills (HumanSkillOptions)
  kRobotPolicy,  // scripted robot behaviour (RobotPolicyOptions)
};

struct ControllerSpec {
  ControllerKind kind = ControllerKind::kRobotPolicy;
  HumanSkillOptions human;
  RobotPolicyOptions robot;
};

struct EpisodeSpec {
  SceneSpec scene;
  ControllerSpec controller;
  int num_steps = 64;                      // T, the number of recorded frames
  uint64_t seed = 0;                       // controller randomness (the scene has its own seed)
  bool render = true;                      // false: frames stay empty (fast policy evaluation)
  std::vector<std::string> extra_cameras;  // rendered beside "ego" each step (e.g. "side")
  int settle_steps = 5;                    // control steps before frame 0
  int final_settle_steps = 20;             // steps after the last action before measuring success
};

struct EpisodeRecord {
  int width = 0;
  int height = 0;
  std::vector<std::vector<uint8_t>> frames;  // T x [H, W, 3] uint8, top row first
  // Per extra camera, in EpisodeSpec::extra_cameras' order: its T frames as `frames`.
  std::vector<std::pair<std::string, std::vector<std::vector<uint8_t>>>> views;
  std::vector<std::vector<float>> actions;        // robot: T x 6; human: empty
  std::vector<std::vector<float>> states;         // robot: T x 6; human: empty
  std::vector<std::vector<float>> hidden_motion;  // T x 6 (human) / T x 5 (robot); never train on it
  // T x 9: (u, v, in_view) of the 3 keypoints (World::keypoints) with each frame; never train on it.
  std::vector<std::vector<float>> keypoints;
  // Robot scenes with a bin: bin_success() after the final settle; NaN otherwise.
  double success = std::numeric_limits<double>::quiet_NaN();
  // embodiment, task (instruction text), skills (human skill names in order / robot behaviour),
  // controller (full description with sampled parameters), scene (to_json, incl. objects and
  // background), novel_background, ood_objects, fps, num_steps, seed, scene_seed, width, height,
  // action_names, state_names, hidden_motion_names, keypoint_names, object_outcomes, success
  // (null for human).
  nlohmann::json meta;
};

// Runs an episode. Uses `renderer` when given (it must be used from this thread only), else a
// thread-local one. Throws dojo::Error on invalid specs or diverging physics.
EpisodeRecord run_episode(const EpisodeSpec& spec, Renderer* renderer = nullptr);

// Convenience: a default controller spec for an embodiment (human: random chained skills;
// robot: expert bin policy).
ControllerSpec default_controller(Embodiment embodiment);

}  // namespace dojo::sim
