// `dojo value train` and `dojo plan`: the value model trained on the demonstrators' labelled
// episodes, and planning over DojoSim scenes with proposals from policy checkpoints, against the
// baselines on the same scenes (recipes/planning.h says what a decision is).
#pragma once

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "recipes/planning.h"
#include "recipes/policy_eval.h"

namespace dojo::recipes {

struct ValueRun {
  std::string out = "dojo_plan/value";
  int64_t episodes = 130, steps = 1500, batch = 64, horizon = 32, accumulate = 1;
  uint64_t seed = 40000;
};
// OUT/data.safetensors (rendered once; OUT/data.json records its seeds), OUT/checkpoint,
// OUT/result.json (held-out error in steps, order accuracy).
nlohmann::json train_value(const ValueRun& run);

struct PlanRun {
  std::string out = "dojo_plan";
  // Where proposals are imagined: this world model; none: DojoSim (the exact imagination).
  std::optional<WorldModelSource> world_model;
  std::string value;  // value model checkpoint ("": OUT/value, trained here when missing)
  ValueRun value_training;
  std::vector<std::filesystem::path> proposers;  // policy checkpoints (behaviour cloning)
  int64_t scenes = 30, videos = 1;
  uint64_t seed = 7000;
  PlanningOptions options;
};

// The report: success with planning, with a random proposal per decision and with each proposer
// alone, per scene and in total; the decision latency. OUT/report.json, OUT/report.html,
// OUT/journal.jsonl (finished episodes; a rerun resumes).
struct PlanReport {
  std::vector<std::string> proposers;
  double plan = 0, random = 0, best_single = 0;  // success rates over the scenes
  std::string best_proposer;
  std::vector<double> single;   // per proposer
  double decision_seconds = 0;  // mean over planning's decisions
  int64_t proposals = 0;
  nlohmann::json to_json() const;
};
PlanReport run_planning(const PlanRun& run);

}  // namespace dojo::recipes
