// Dataset generation from DojoSim: many episodes of one embodiment and split, written in the
// episode-store format (data/episode_store.h). Deterministic for a seed (each episode's seeds
// derive from (seed, episode index) alone, so the worker count changes nothing), parallel,
// and resumable: finished episodes are kept, half-written ones are discarded and redone.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "data/episode_store.h"
#include "sim/skills.h"

namespace dojo::sim {

// The benchmark splits mirroring the paper's evaluation.
//   train            training data (robot: bin task at mixed policy quality, with a validation
//                    tail marked "val" = the in-distribution validation split)
//   ood-objects      robot acting on objects only the human embodiment touched
//   counterfactual   robot patting, reaching and missing, pushing, moving at random
//   novel-background robot bin task in front of backgrounds never used for training
//   long-horizon     robot bin task over 600 frames (60 s at 10 Hz)
const std::vector<std::string>& split_names();
// The robot behaviours that are play (--play-behaviors): random_motion and teleop_play (an
// operator's held keys).
const std::vector<std::string>& play_behavior_names();

struct GenerateOptions {
  std::string embodiment = "robot";  // human | robot
  std::string split = "train";
  int episodes = 16;
  int frames = 0;  // 0: the split's default (64; long-horizon 600)
  int width = 64;
  int height = 64;
  uint64_t seed = 0;
  int workers = 0;                  // 0: all cores
  double val_fraction = 0.125;      // robot train split: share of episodes marked "val"
  std::vector<std::string> skills;  // human: restrict to these skills (default: all)
  std::string quality;              // robot bin policy preset; empty = mix of expert/good/medium
  // Robot train split: share of episodes that are "play" (random_motion: the arm moves to random
  // reachable poses with random gripper commands) instead of the bin task. Demonstrations make
  // the next motion predictable from the scene; play data is where a world model must read the
  // actions to know where the arm goes.
  double play_fraction = 0;
  // The play episodes' behaviours, in turn (episode i the (i mod n)-th), of play_behavior_names().
  // Empty: random_motion.
  std::vector<std::string> play_behaviors;
  // Robot train split: each episode that is not play runs one of these in turn (episode i the
  // (i mod n)-th; a named behaviour and quality: a policy set, as `dojo policy eval` uses) instead
  // of the expert/good/medium mix; the name goes into the episode's meta as "policy". A world
  // model trained only on near-expert demonstrations has never seen an arm hold still, dawdle or
  // drop its object, and evaluating such policies in it needs it to have.
  struct NamedPolicy {
    std::string name;
    RobotPolicyOptions options;
  };
  std::vector<NamedPolicy> policies;
  // Cameras recorded beside "ego", each as <camera>.mp4 in every episode ("side": a fixed view
  // from the table's right). Multi-view training tiles them (data/multi_view.h).
  std::vector<std::string> cameras;
  // How the episodes store their frames (data::VideoFormat): raw needs no video library.
  data::VideoFormat video_format = data::VideoFormat::kMp4;

  nlohmann::json to_json() const;
};

struct GenerateSummary {
  int generated = 0;   // episodes made by this run
  int reused = 0;      // episodes found complete from an earlier run
  int64_t frames = 0;  // frames made by this run
  double seconds = 0;
  double mean_success = 0;  // robot bin task: mean success over all episodes; NaN otherwise
};

// Generates into `out` (created if needed). A directory holding a run with different options
// is refused with an error naming the differing field.
GenerateSummary generate_dataset(const std::filesystem::path& out, const GenerateOptions& options);

}  // namespace dojo::sim
