// `dojo value train` and `dojo plan`: planning with a value model over DojoSim scenes
// (recipes/plan_run.h; docs/planning.md).
#include <CLI/CLI.hpp>

#include <cstdio>
#include <memory>

#include "cli/commands.h"
#include "cli/options.h"
#include "cli/world_model_args.h"
#include "core/error.h"
#include "core/runtime.h"
#include "recipes/plan_run.h"
#include "train/train_util.h"

namespace dojo::cli {
namespace {

struct PlanArgs {
  recipes::PlanRun run;
  WorldModelArgs wm;
  std::string imagination = "world-model";
  std::vector<std::string> proposers;
  std::string bc = "dojo_policy/bc";
};

int run_plan(PlanArgs a) {
  DOJO_CHECK(a.proposers.empty() || a.proposers.size() >= 2, "plan: give at least two --proposers");
  if (a.proposers.empty()) {
    for (const auto& snapshot : train::list_step_snapshots(a.bc)) a.run.proposers.push_back(snapshot);
    DOJO_CHECK(a.run.proposers.size() >= 2,
               a.bc + ": fewer than two policy snapshots to propose from (run `dojo policy train --out " +
                   a.bc + " --snapshots ...`, or give --proposers)");
  } else {
    for (const auto& p : a.proposers) a.run.proposers.emplace_back(p);
  }
  if (a.imagination == "world-model") a.run.world_model = resolve_world_model(a.wm, "plan");
  ScopedThreads matmul_bound(matmul_bound_command_threads("plan", parse_device(a.wm.device).is_cuda()));
  const auto report = recipes::run_planning(a.run);
  std::printf("%-28s %8s\n", "commands chosen by", "success");
  std::printf("%-28s %8.3f\n", "planning", report.plan);
  std::printf("%-28s %8.3f\n", "a random proposal", report.random);
  for (size_t k = 0; k < report.proposers.size(); ++k)
    std::printf("%-28s %8.3f\n", (report.proposers[k] + " alone").c_str(), report.single[k]);
  std::printf(
      "planning %+.3f over the best single proposer (%s), %+.3f over a random choice; %.2f s a decision "
      "(%lld proposals imagined)\n",
      report.plan - report.best_single, report.best_proposer.c_str(), report.plan - report.random,
      report.decision_seconds, static_cast<long long>(report.proposals));
  return 0;
}

}  // namespace

void register_plan(CLI::App& app) {
  auto* value = app.add_subcommand("value", "The value model that planning scores imagined videos with");
  value->require_subcommand(1);
  auto v = std::make_shared<recipes::ValueRun>();
  auto* train_cmd = value->add_subcommand(
      "train",
      "Render the scripted demonstrators' episodes in DojoSim, label every frame with the steps to the "
      "next subtask boundary (reach, lift, over the bin, release) and train the value model (resumable)");
  train_cmd->add_option("--out", v->out, "Output directory")->capture_default_str();
  train_cmd->add_option("--episodes", v->episodes, "Labelled episodes")
      ->check(CLI::Range(2, 1000000))
      ->capture_default_str();
  train_cmd->add_option("--seed", v->seed, "First scene seed (keep apart from the planning scenes)")
      ->capture_default_str();
  train_cmd->add_option("--steps", v->steps, "Training steps")
      ->check(CLI::Range(0, 10000000))
      ->capture_default_str();
  train_cmd->add_option("--batch", v->batch, "Batch size")->check(CLI::Range(1, 4096))->capture_default_str();
  train_cmd->add_option("--horizon", v->horizon, "Control steps a value of 1 stands for")
      ->check(CLI::Range(1, 10000))
      ->capture_default_str();
  add_accumulate_option(train_cmd, v->accumulate);
  train_cmd->callback([v] { set_action([v] { return recipes::train_value(*v).is_object() ? 0 : 1; }); });

  auto p = std::make_shared<PlanArgs>();
  auto* plan = app.add_subcommand(
      "plan",
      "Plan in DojoSim: at each decision every proposer's action chunk is imagined in the world model and "
      "scored by the value model, the best executed; against a random proposal and each proposer alone, "
      "on the same scenes; JSON + HTML (resumable)");
  plan->add_option("--out", p->run.out, "Output directory")->capture_default_str();
  plan->add_option("--proposers", p->proposers,
                   "Policy checkpoints that propose action chunks (behaviour-cloning snapshots; default: "
                   "every snapshot of --bc)")
      ->delimiter(',');
  plan->add_option("--bc", p->bc, "A `dojo policy train` run whose snapshots propose")->capture_default_str();
  plan->add_option("--value", p->run.value, "Value model (default: OUT/value, trained when missing)");
  plan->add_option("--value-steps", p->run.value_training.steps,
                   "Training steps when the value model is trained here")
      ->capture_default_str();
  plan->add_option(
          "--imagination", p->imagination,
          "Where proposals are imagined: the world model, or DojoSim itself (the planner's upper bound)")
      ->check(CLI::IsMember({"world-model", "simulator"}))
      ->capture_default_str();
  add_world_model_options(plan, p->wm);
  plan->add_option("--scenes", p->run.scenes, "DojoSim scenes")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  plan->add_option("--seed", p->run.seed, "First scene seed")->capture_default_str();
  plan->add_option("--frames", p->run.options.frames, "Commands an episode acts for")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  plan->add_option("--decide-every", p->run.options.decide_every, "Commands executed between decisions")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  plan->add_option("--proposal-length", p->run.options.proposal_length,
                   "Commands a proposal holds and is imagined for (a multiple of the world model's step)")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  plan->add_option("--videos", p->run.videos,
                   "Scenes whose first decision is filmed (OUT/videos, in the report)")
      ->check(CLI::Range(0, 100000))
      ->capture_default_str();
  plan->callback([p] { set_action([p] { return run_plan(*p); }); });
}

}  // namespace dojo::cli
