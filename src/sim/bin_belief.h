// The bin task as a vision-only policy knows it: a belief about the one object and the bin, read
// from a frame (recipes/vision_policies.h trains the reader), and a controller that plans the bin
// policy's attempts from that belief instead of from simulator state.
//
// The controller knows its own body (the arm's kinematics, its start command, the control rate),
// never the scene: at the start of each attempt it asks for a fresh belief, so a grasp that missed
// (the object still on the table in the next frame) is tried again, and an object it sees in the
// bin ends the task. The same belief computed from simulator state (true_bin_belief) is the
// reader's training label.
#pragma once

#include <cstdint>
#include <memory>
#include <nlohmann/json.hpp>
#include <vector>

#include "sim/rng.h"

namespace dojo::sim {

class Script;
class World;

struct BinBelief {
  double object_x = 0, object_y = 0;  // the object's centre on the table (m, world frame)
  double grasp_z = 0.03;              // the grasp point's height that takes it (m)
  double drop_offset = 0.03;          // grasp point above the object's lowest point (m)
  double roll = 0;                    // wrist roll aligning the fingers with its faces (rad; mod pi)
  double bin_x = 0.16, bin_y = 0.14;  // the bin's centre (m)

  // As the reader's targets: x, y, grasp_z, drop_offset, cos 2 roll, sin 2 roll, bin_x, bin_y
  // (the fingers are symmetric, so the roll is read modulo pi).
  static constexpr int kValues = 8;
  std::vector<double> to_values() const;
  static BinBelief from_values(const std::vector<double>& values);  // throws dojo::Error on a wrong size
  // The object's centre within the bin's inner walls (the bin of DojoSim's robot scenes).
  bool object_in_bin() const;
};

// The belief as simulator state has it (object 0); throws dojo::Error without a bin or an object.
BinBelief true_bin_belief(const World& world);

struct BeliefControllerOptions {
  std::vector<double> start_command;  // the command in force at frame 0 (6 values): home
  double control_dt = 0;              // seconds per control step (the world's rate)
  double speed = 1.0;                 // motion speed multiplier
  double noise_std = 0.0;             // smooth AR(1) noise on the joint targets, rad
  int max_attempts = 3;               // grasps before going home
  uint64_t seed = 0;                  // the noise's seed
};

class BeliefBinController {
 public:
  explicit BeliefBinController(const BeliefControllerOptions& options);
  ~BeliefBinController();
  // Whether the command of control step `step` starts a new plan (and so uses a fresh belief).
  bool plans_at(int step) const;
  // The command of control step `step` (0, 1, ... in order); `belief` is read only when
  // plans_at(step).
  std::vector<double> act(const BinBelief& belief, int step);
  int attempts() const { return attempts_; }
  bool finished() const { return finished_; }
  nlohmann::json describe() const;

 private:
  void plan(const BinBelief& belief, double now);
  void timed(const std::vector<double>& pose, double seconds);
  void move(const std::vector<double>& pose);

  BeliefControllerOptions options_;
  Rng rng_;
  std::vector<double> home_;        // [x, y, z, wrist roll, gripper] of the start command
  std::vector<double> noise_;       // [5] joint noise state
  std::unique_ptr<Script> script_;  // Cartesian keyframes [x, y, z, wrist roll, gripper]
  int attempts_ = 0;
  bool finished_ = false;
  nlohmann::json log_ = nlohmann::json::array();
};

}  // namespace dojo::sim
