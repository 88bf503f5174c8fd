// Vision-only policies for policy evaluation (eval/policy_eval.h): policies that see the frames
// and their own commands, never simulator state, so that in the world model they act on what it
// generates. Two families, each graded:
//  - behaviour cloning (models/bc_policy.h): snapshots of one run along its training;
//  - readers: a scene reader (models/scene_reader.h) reads the object's and the bin's positions
//    off the newest frame at the start of every attempt, and the belief controller
//    (sim/bin_belief.h) plans the bin policy's grasp from that reading; graded by the reader's
//    training steps and by the controller's speed, noise and number of tries.
// DojoSim's scripted planners (recipes/dojosim_policies.h) stay the demonstrators: they make the
// behaviour-cloning data, the reader's data and the success detector's, and are never in the
// default evaluated set, so that set is held out from everything the evaluation learnt from.
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "eval/policy_eval.h"
#include "recipes/dojosim_policies.h"

namespace dojo::recipes {

// Frames of the demonstrators' episodes labelled with sim::true_bin_belief (train/reader_train.h's
// SceneReadings): the bin policy at several qualities (misses, drops, wrong places: the object
// seen on the table, in the gripper, in and beside the bin) and pushes, on policy scenes of seeds
// seed, seed + 1, ... (keep them apart from the evaluation's).
struct ReaderDataOptions {
  int64_t episodes = 160;
  uint64_t seed = 30000;
  int size = 64;
  int64_t frames = 64;  // control steps per episode
  int64_t every = 2;    // a labelled frame every this many steps
  double heldout_fraction = 0.1;
};
// Writes the file atomically.
void make_reader_data(const ReaderDataOptions& options, const std::filesystem::path& path);

// The controller knobs of a reader policy: {"speed": 1, "noise_std": 0, "max_attempts": 3}
// (absent ones keep these values); throws dojo::Error naming `where` for another key or a bad value.
struct ReaderKnobs {
  double speed = 1.0, noise_std = 0.0;
  int max_attempts = 3;
  static ReaderKnobs from_json(const nlohmann::json& j, const std::string& where);
  nlohmann::json to_json() const;
};

// A reader policy (spec.reader names the reader checkpoint, spec.quality its knobs).
std::unique_ptr<eval::Policy> make_reader_policy(const PolicySpec& spec);

// The default evaluated set: every snapshot of the behaviour-cloning run in `bc_dir` (bc-STEP), every
// snapshot of the reader run in `reader_dir` at full quality (reader-STEP), and the last reader
// with the controller's knobs turned (reader-slow, -hasty, -noisy, -very-noisy, -one-try,
// -noisy-one-try). An empty directory leaves its family out; throws dojo::Error naming a directory
// that holds no snapshot.
std::vector<PolicySpec> vision_policy_set(const std::filesystem::path& bc_dir,
                                          const std::filesystem::path& reader_dir);

// Scene seeds a part of the evaluation draws from, [first, first + count).
struct SeedRange {
  std::string what;  // "the evaluation's scenes", "the detector's episodes", ...
  uint64_t first = 0;
  int64_t count = 0;
};
// Throws dojo::Error naming both parts when two ranges share a seed: held out by construction.
void check_disjoint_seeds(const std::vector<SeedRange>& ranges);

}  // namespace dojo::recipes
