// Model-based planning with a value model (the paper's test-time use): at each decision point a
// set of proposers (policy checkpoints) each propose an action chunk from the frames seen so far;
// every proposal is imagined (rolled out in the world model from the current frame, or in a copy of
// the simulator), the imagined video is scored by the value model (models/value_model.h: lower is
// closer to the next subtask boundary), and the first commands of the best proposal are executed
// in DojoSim. Until the episode's end; success is DojoSim's.
//
//   frames = [env.reset(start)]
//   every `decide_every` commands:  proposals_k = proposer_k.propose(frames, last, step, length)
//                                   video_k = imagine(current frame, last, proposals_k)
//                                   value_k = video_value(window_values(last frames + video_k))
//                                   execute proposals_argmin[0 : decide_every] in DojoSim
//
// Baselines on the same scenes: a uniformly random proposal at each decision (no imagination), and
// each proposer alone.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "eval/policy_eval.h"
#include "models/bc_policy.h"
#include "models/value_model.h"

namespace dojo::recipes {

// Labelled episodes for the value model: the scripted bin-task demonstrators that carry on toward
// the bin (expert to poor, slow, noisy, late, misses-half) in turn on policy scenes of
// seeds seed, seed + 1, ... (kept apart from the evaluation's), every frame labelled with the
// control steps to the episode's next subtask boundary (sim::bin_task_stage rising): 0 from the
// moment the task is done, `horizon` past the last boundary of an episode that fails.
struct ValueDataOptions {
  int64_t episodes = 130;
  uint64_t seed = 40000;
  int size = 64;
  int64_t frames = 64, settle_frames = 12;
  int64_t horizon = 32;
  double heldout_fraction = 0.2;
};
void make_value_data(const ValueDataOptions& options, const std::filesystem::path& path);  // atomically

// Proposes the next `n` commands [n, w] from the frames shown so far [T, H, W, 3] uint8 (the newest
// last), the command in force [w] and the control step.
class Proposer {
 public:
  virtual ~Proposer() = default;
  virtual const std::string& name() const = 0;
  virtual void reset(const eval::EpisodeStart& start) = 0;
  virtual torch::Tensor propose(const torch::Tensor& frames, const torch::Tensor& last_command, int64_t step,
                                int64_t n) = 0;
};
// A behaviour-cloning checkpoint: its chunk from the newest frame (n <= its chunk).
std::unique_ptr<Proposer> make_bc_proposer(std::string name, models::BcPolicy policy);

// Where proposals are imagined.
struct ImaginationRequest {
  const eval::EpisodeStart* start = nullptr;  // the episode's start
  torch::Tensor frame;                        // the newest real frame [H, W, 3]
  torch::Tensor last_command;                 // [w]
  torch::Tensor executed;                     // every command executed so far [N, w] (N may be 0)
  uint64_t seed = 0;                          // for the world model's noise
};
class Imagination {
 public:
  virtual ~Imagination() = default;
  virtual std::string name() const = 0;
  // The frames `proposal` [n, w] leads to, [n, H, W, 3] uint8.
  virtual torch::Tensor imagine(const ImaginationRequest& request, const torch::Tensor& proposal) = 0;
};
// A world model (policy_eval.h's environment) started from the newest real frame.
std::unique_ptr<Imagination> make_world_model_imagination(eval::Environment& world_model);
// DojoSim itself: the scene replayed up to now, then the proposal (exact, for checking the planner).
std::unique_ptr<Imagination> make_simulator_imagination();

// Scores an imagined video (the last real frames first, then the imagined ones); lower wins.
class Scorer {
 public:
  virtual ~Scorer() = default;
  virtual double score(const torch::Tensor& video) = 0;  // [T, H, W, 3] uint8
};
std::unique_ptr<Scorer> make_value_scorer(models::ValueModel model);

struct PlanningOptions {
  int64_t frames = 64, settle_frames = 12;  // as policy evaluation's episodes
  int64_t decide_every = 8;                 // commands executed between decisions
  int64_t proposal_length = 16;             // commands a proposal holds (and is imagined for)
  int64_t context = 3;                      // real frames before the imagined ones the scorer sees
};

enum class Choice { kPlan, kRandom, kFixed };

struct PlanEpisode {
  double success = 0;
  int64_t decisions = 0;
  std::vector<int> chosen;                   // the proposer chosen at each decision
  std::vector<std::vector<double>> values;   // per decision, per proposer (planning only)
  double seconds = 0, decision_seconds = 0;  // the episode; the mean decision (imagining and scoring)
  nlohmann::json to_json() const;
};

// One episode in DojoSim from `start`. kPlan needs `imagination` and `scorer`; kFixed uses proposer
// `fixed` alone; kRandom draws a proposer per decision from `seed`. With `imagined`, the first
// decision's imagined videos are appended to it (one [n, H, W, 3] per proposer: the report's example).
PlanEpisode plan_episode(const eval::EpisodeStart& start, const std::vector<Proposer*>& proposers,
                         Imagination* imagination, Scorer* scorer, Choice choice, int fixed,
                         const PlanningOptions& options, uint64_t seed,
                         std::vector<torch::Tensor>* imagined = nullptr);

}  // namespace dojo::recipes
