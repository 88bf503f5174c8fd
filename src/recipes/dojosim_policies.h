// DojoSim's side of policy evaluation (eval/policy_eval.h): the scenes, the simulator as the
// "real" world, scripted policies of graded quality, and the labelled episodes the success
// detector learns from.
//
// Scenes: robot, one object of the robot's set, the bin (so an episode either succeeds or fails),
// the training backgrounds. Frame 0 is the scene after sim::EpisodeSpec's settle steps at the rest pose, as
// in the generated datasets.
//
// Scripted policies plan at reset: they build their own copy of the scene from its description
// and run DojoSim's bin policy (sim/skills.h) in it, with the quality knobs set (noise, delay,
// misses, wrong targets, early release, speed). From then on they replay that plan and never look
// at a frame: open loop, so in the simulator they do exactly what the state-based controller would
// and in the world model they test whether it predicts the outcome of the same commands.
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "eval/policy_eval.h"

namespace dojo::sim {
class Renderer;
class World;
struct RobotPolicyOptions;
}  // namespace dojo::sim

namespace dojo::recipes {

struct PolicySceneOptions {
  int64_t count = 30;
  uint64_t seed = 7000;  // scene i has seed + i (evaluation scenes; training data uses others)
  int size = 64;         // frame size
};
std::vector<eval::EpisodeStart> make_policy_scenes(const PolicySceneOptions& options);

// The simulator as an environment: success is bin_success of its state after the last step.
class DojoSimEnvironment : public eval::Environment {
 public:
  DojoSimEnvironment();
  ~DojoSimEnvironment() override;
  std::string name() const override { return "DojoSim"; }
  torch::Tensor reset(const eval::EpisodeStart& start) override;
  torch::Tensor step(const torch::Tensor& commands) override;
  double success() override;
  // bin_success of the current state (the success detector's label for the newest frame).
  double success_now() const;
  const sim::World& world() const { return *world_; }

 private:
  std::unique_ptr<sim::World> world_;
  std::unique_ptr<sim::Renderer> renderer_;
};

// One policy of an evaluation, as a policy-set file names it. Scripted (the default): DojoSim's bin
// policy at a quality (sim::PolicyQuality) or another behaviour ("idle", "random_motion", "push",
// ... as in sim/skills.h). Learned: a behaviour-cloning checkpoint
// (models/bc_policy.h). External: a command whose process speaks the step protocol
// (serve/external_policy.h). The CLI turns specs into policies (learned and external ones need
// layers beside this one).
struct PolicySpec {
  std::string name;
  std::string behavior = "bin_pick";  // a sim::RobotBehavior name (bin_pick, idle, random_motion, ...)
  nlohmann::json quality = "expert";  // a preset name or {noise_std, delay_steps, miss_prob, ...}
  std::filesystem::path checkpoint;   // non-empty: a learned policy
  std::string command;                // non-empty: an external policy
  // Non-empty: a reader policy (recipes/vision_policies.h) with this scene reader; `quality` then
  // holds its controller's knobs (ReaderKnobs).
  std::filesystem::path reader;

  bool scripted() const { return checkpoint.empty() && command.empty() && reader.empty(); }
};
// Throws dojo::Error unless `spec` is scripted.
std::unique_ptr<eval::Policy> make_scripted_policy(const PolicySpec& spec);
// What the simulator runs for a scripted spec (its behaviour and quality knobs); throws dojo::Error
// naming the policy for an unknown behaviour or knob.
sim::RobotPolicyOptions scripted_policy_options(const PolicySpec& spec);

// The built-in policy set: 13 scripted policies from expert to idle.
std::vector<PolicySpec> default_policy_set();

// A command row [w] as the simulator takes it.
std::vector<double> command_values(const torch::Tensor& row);
// {"policies": [{"name": ..., "behavior": ..., "quality": ...} | {"name": ..., "checkpoint": DIR} |
// {"name": ..., "reader": DIR, "quality": {knobs}} | {"name": ..., "command": "..."}, ...]}; a
// relative checkpoint or reader is relative to the file. Throws
// dojo::Error naming the file and the entry.
std::vector<PolicySpec> read_policy_set(const std::filesystem::path& path);

// Episodes of the given policies in DojoSim on scenes seed, seed + 1, ..., every frame labelled
// with the simulator's success; `heldout_fraction` of the scenes (the last ones) are held out.
struct SuccessDataOptions {
  int64_t scenes = 24;
  uint64_t seed = 9000;
  int size = 64;
  double heldout_fraction = 0.25;
  eval::PolicyEvalOptions episode;  // the same episode length as the evaluation
};
// Writes a train::SuccessData file to `path` (atomically). With `frames_from` (a world model), the
// frames are that world's replay of the same commands while the labels stay the simulator's: the
// scripted policies plan at reset and never look at a frame, so both worlds receive identical
// commands and the detector learns what success looks like in generated video. A step takes the
// world's own actions_per_step() commands when it has one, else options.episode.actions_per_step.
void make_success_data(const std::vector<PolicySpec>& policies, const SuccessDataOptions& options,
                       const std::filesystem::path& path, eval::Environment* frames_from = nullptr);

// Demonstrations for the behaviour-cloning policy (train/bc_train.h): DojoSim's expert bin policy
// on policy scenes (seeds seed, seed + 1, ...: keep them apart from the evaluation's), watching
// the real state. Smooth noise is injected into the executed arm commands while the labels stay
// the expert's (DART), so the cloned policy sees, and learns to leave, states off the expert's path.
struct DemonstrationOptions {
  int64_t episodes = 400;
  uint64_t seed = 20000;
  int size = 64;
  int64_t frames = 64;      // control steps per episode
  double noise_std = 0.03;  // rad, AR(1) noise on the executed arm joints (0: none)
  double heldout_fraction = 0.1;
};
// Writes a train::Demonstrations file to `path` (atomically).
void make_demonstrations(const DemonstrationOptions& options, const std::filesystem::path& path);

}  // namespace dojo::recipes
