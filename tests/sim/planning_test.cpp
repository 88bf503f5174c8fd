// Planning with a value model (recipes/planning.h, recipes/plan_run.h): a video's value stops at
// the dip before a boundary; the value data marks DojoSim's subtask boundaries; the value model
// learns on DojoSim clips; with the simulator as the imagination and the true value the planner
// beats a random choice among the same proposals; `dojo value train` and `dojo plan` end to end.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <fstream>
#include <nlohmann/json.hpp>

#include "core/checkpoint.h"
#include "core/error.h"
#include "models/bc_policy.h"
#include "models/value_model.h"
#include "recipes/dojosim_policies.h"
#include "recipes/planning.h"
#include "sim/policy_scenes.h"
#include "sim/task.h"
#include "sim/world.h"
#include "test_util.h"
#include "train/value_train.h"

namespace dojo::recipes {
namespace {

namespace fs = std::filesystem;

TEST(Planning, VideoValueStopsAtTheRiseAfterADip) {
  EXPECT_DOUBLE_EQ(models::video_value({0.5, 0.4, 0.3, 0.8, 0.7}), 0.4);
  EXPECT_DOUBLE_EQ(models::video_value({0.5, 0.45, 0.4}), 0.45);
  EXPECT_DOUBLE_EQ(models::video_value({0.2, 0.25, 0.28}), (0.2 + 0.25 + 0.28) / 3);  // a rise under 0.1
  EXPECT_THROW(models::video_value({}), Error);
}

// The expert's labelled episode counts down to each boundary and reads 0 once the task is done.
TEST(Planning, ValueDataCountsDownToEachSubtaskBoundary) {
  test::OneThread one;
  test::TempDir tmp;
  ValueDataOptions o;
  o.episodes = 1;  // the first demonstrator: the expert
  o.heldout_fraction = 0;
  make_value_data(o, tmp / "value.safetensors");
  const auto data = train::ValueData::load(tmp / "value.safetensors");
  ASSERT_EQ(data.frames.size(1), 1 + 64 + 12);
  const auto steps = data.steps_to_boundary[0];
  EXPECT_EQ(steps[-1].item<float>(), 0.0f) << "the expert's episode ends done";
  int64_t zeros_before_done = 0;
  for (int64_t t = 0; t + 1 < steps.size(0); ++t) {
    const float now = steps[t].item<float>(), next = steps[t + 1].item<float>();
    if (now > 0) {
      EXPECT_EQ(next, now - 1) << "frame " << t;  // counting down to the next boundary
    }
    zeros_before_done += now == 0 && next > 0;
  }
  EXPECT_GE(zeros_before_done, 2) << "reach, lift and over-the-bin boundaries before the release";
}

// The value model fits DojoSim's labelled clips (held-out generalisation is measured at full scale
// in docs/benchmarks.md: 260 episodes, 1500 steps).
TEST(Planning, ValueModelLearnsOnDojoSimClips) {
  test::OneThread one;
  test::TempDir tmp;
  ValueDataOptions o;
  o.episodes = 8;
  o.heldout_fraction = 0.25;
  make_value_data(o, tmp / "value.safetensors");
  train::ValueTrainJob job;
  job.data = tmp / "value.safetensors";
  job.out = tmp / "value";
  job.steps = 500;
  job.batch_size = 32;
  const auto data = train::ValueData::load(job.data);
  const auto trained_on = data.heldout.logical_not();
  torch::manual_seed(job.seed);
  auto untrained = models::make_value_model();
  const auto before = train::value_errors(untrained, data, trained_on);
  train::run_value_training(job);
  auto model = models::load_value_model(tmp / "value" / "checkpoint");
  EXPECT_EQ(model.horizon, 32);
  EXPECT_EQ(model.window(), 4);
  const auto after = train::value_errors(model, data, trained_on);
  EXPECT_GT(after.windows, 0);
  EXPECT_LT(after.mean_abs_steps, 0.6 * before.mean_abs_steps) << before.mean_abs_steps;
  EXPECT_GT(after.order_accuracy, 0.7) << before.order_accuracy;
}

// A scripted plan indexed by the control step (planned at reset in its own copy of the scene): a
// proposer of known quality for checking the planner, which the test lets read the scene.
class PlanProposer : public Proposer {
 public:
  explicit PlanProposer(PolicySpec spec) : spec_(std::move(spec)) {}
  const std::string& name() const override { return spec_.name; }
  void reset(const eval::EpisodeStart& start) override {
    auto policy = make_scripted_policy(spec_);
    policy->reset(start);
    plan_ = policy->act(start.frame.unsqueeze(0), start.command, 96);  // [96, 6]
  }
  torch::Tensor propose(const torch::Tensor&, const torch::Tensor&, int64_t step, int64_t n) override {
    return plan_.narrow(0, step, n).clone();
  }

 private:
  PolicySpec spec_;
  torch::Tensor plan_;
};

// The simulator's own progress at the end of an imagined proposal, as a value (lower wins): the
// subtasks left, then how far the next one is.
class TrueValue : public Imagination, public Scorer {
 public:
  std::string name() const override { return "DojoSim with the true value"; }
  torch::Tensor imagine(const ImaginationRequest& request, const torch::Tensor& proposal) override {
    env_.reset(*request.start);
    if (request.executed.defined() && request.executed.size(0) > 0) env_.step(request.executed);
    const auto frames = env_.step(proposal);
    const auto& w = env_.world();
    const int stage = sim::bin_task_stage(w);
    const auto object = w.object_pose(0).pos;
    const auto grasp = w.grasp_point();
    const auto& bin = w.spec().bin.center;
    double far = 0;
    if (stage == 0) far = std::hypot(grasp[0] - object[0], grasp[1] - object[1], grasp[2] - object[2]);
    if (stage == 2) far = std::hypot(object[0] - bin[0], object[1] - bin[1]);
    value_ = (sim::kBinTaskStages - stage) + std::min(far / 0.5, 0.99);
    return frames;
  }
  double score(const torch::Tensor&) override { return value_; }

 private:
  DojoSimEnvironment env_;
  double value_ = 0;
};

TEST(Planning, WithTheSimulatorAndTheTrueValueBeatsARandomChoice) {
  test::OneThread one;
  std::vector<std::unique_ptr<Proposer>> owned;
  std::vector<Proposer*> proposers;
  for (const auto& spec : default_policy_set())
    if (spec.name == "expert" || spec.name == "idle" || spec.name == "wrong-place" || spec.name == "random") {
      owned.push_back(std::make_unique<PlanProposer>(spec));
      proposers.push_back(owned.back().get());
    }
  ASSERT_EQ(proposers.size(), 4u);
  TrueValue truth;
  PlanningOptions options;
  options.decide_every = 16;  // 4 decisions: each imagines by replaying the episode so far
  double planned = 0, random = 0;
  const auto starts = test::policy_scenes(4);
  for (const auto& start : starts) {
    const auto plan = plan_episode(start, proposers, &truth, &truth, Choice::kPlan, -1, options, start.seed);
    EXPECT_EQ(plan.decisions, 4);
    ASSERT_EQ(plan.values.size(), 4u);
    EXPECT_EQ(plan.values[0].size(), 4u);
    planned += plan.success;
    random +=
        plan_episode(start, proposers, nullptr, nullptr, Choice::kRandom, -1, options, start.seed).success;
  }
  EXPECT_GE(planned, 3.0) << "planning succeeded in " << planned << " of 4 scenes";
  EXPECT_GE(planned, random + 2.0) << "a random choice succeeded in " << random;
}

}  // namespace
}  // namespace dojo::recipes

namespace dojo::recipes {
namespace {

TEST(PlanCli, ValueTrainThenPlanWithTheSimulatorResumesAndRefusesBadInput) {
  test::TempDir tmp;
  auto r = test::run_dojo("--threads 1 value train --episodes 3 --steps 3 --batch 4 --out " +
                          (tmp / "value").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto made = nlohmann::json::parse(test::read_file(tmp / "value" / "data.json"));
  EXPECT_EQ(made.at("seed"), 40000);
  EXPECT_TRUE(nlohmann::json::parse(test::read_file(tmp / "value" / "result.json"))
                  .at("heldout")
                  .contains("mean_abs_steps"));
  torch::manual_seed(5);
  for (const char* name : {"a", "b"})
    save_checkpoint(tmp / name, models::bc_policy_checkpoint(*models::BcPolicy()));
  const std::string common =
      "--threads 1 plan --imagination simulator --scenes 1 --frames 16 --decide-every 8 "
      "--proposal-length 16 --value " +
      (tmp / "value" / "checkpoint").string() + " --out " + (tmp / "plan").string();
  r = test::run_dojo(common + " --proposers " + (tmp / "a").string() + "," + (tmp / "b").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto report = nlohmann::json::parse(test::read_file(tmp / "plan" / "report.json"));
  EXPECT_EQ(report.at("proposers"), (nlohmann::json{"a", "b"}));
  for (const char* key : {"plan", "random", "best_single", "decision_seconds"})
    EXPECT_TRUE(report.contains(key)) << key;
  EXPECT_EQ(report.at("single").size(), 2u);
  EXPECT_NE(test::read_file(tmp / "plan" / "report.html").find("<video"), std::string::npos);
  EXPECT_NE(r.output.find("over the best single proposer"), std::string::npos) << r.output;
  // A rerun finds every episode in the journal: nothing is run again (the timing would differ).
  r = test::run_dojo(common + " --proposers " + (tmp / "a").string() + "," + (tmp / "b").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(nlohmann::json::parse(test::read_file(tmp / "plan" / "report.json")).at("decision_seconds"),
            report.at("decision_seconds"));

  const auto refused = [](const test::CommandResult& res, const std::string& expected) {
    EXPECT_NE(res.exit_code, 0);
    EXPECT_NE(res.output.find(expected), std::string::npos) << res.output;
  };
  refused(test::run_dojo(common + "2 --proposers " + (tmp / "a").string()),
          "plan: give at least two --proposers");
  refused(
      test::run_dojo("plan --imagination simulator --value " + (tmp / "nowhere").string() + " --proposers " +
                     (tmp / "a").string() + "," + (tmp / "b").string() + " --out " + (tmp / "p3").string()),
      "plan: no value model at");
  refused(test::run_dojo("plan --imagination simulator --seed 40001 --value " + (tmp / "value").string() +
                         " --proposers " + (tmp / "a").string() + "," + (tmp / "b").string() + " --out " +
                         (tmp / "p4").string()),
          "and the value model's episodes (seeds 40000-40002) share scenes");
  // A proposal longer than a proposer predicts fails before anything runs.
  refused(test::run_dojo("plan --imagination simulator --proposal-length 24 --value " +
                         (tmp / "value").string() + " --proposers " + (tmp / "a").string() + "," +
                         (tmp / "b").string() + " --out " + (tmp / "p5").string()),
          "predicts 16 commands at a time, fewer than --proposal-length 24");
  // Data made for another horizon is not trained on again.
  refused(test::run_dojo("--threads 1 value train --episodes 3 --steps 3 --batch 4 --horizon 16 --out " +
                         (tmp / "value").string()),
          "was made with horizon 32, not 16: give the settings its data.json records, or another --out");
  // A proposer retrained in place is another planner: the journal of the old one is not resumed.
  torch::manual_seed(6);
  save_checkpoint(tmp / "a", models::bc_policy_checkpoint(*models::BcPolicy()));
  refused(test::run_dojo(common + " --proposers " + (tmp / "a").string() + "," + (tmp / "b").string()),
          "journal.jsonl: written by another planning");
}

}  // namespace
}  // namespace dojo::recipes
