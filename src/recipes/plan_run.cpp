#include "recipes/plan_run.h"

#include <torch/torch.h>

#include <algorithm>
#include <cstdio>
#include <map>

#include "core/atomic_file.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/json_journal.h"
#include "core/log.h"
#include "core/progress.h"
#include "eval/html_report.h"
#include "io/video.h"
#include "recipes/dojosim_policies.h"
#include "recipes/vision_policies.h"
#include "train/value_train.h"

namespace fs = std::filesystem;

namespace dojo::recipes {
namespace {

std::string fixed3(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.3f", v);
  return buf;
}

// A proposer's name: bc-STEP for a snapshot of a `dojo policy train` run, else the directory's name.
std::string proposer_name(const fs::path& dir) {
  const auto leaf = dir.filename().string();
  if (leaf.rfind("step-", 0) == 0 && leaf.size() > 5 &&
      leaf.find_first_not_of("0123456789", 5) == std::string::npos)
    return "bc-" + std::to_string(std::stoll(leaf.substr(5)));
  return leaf;
}

fs::path example_video(const fs::path& dir, int64_t scene) {
  return dir / ("scene-" + std::to_string(scene) + "-decision-0.mp4");
}

std::string mode_name(Choice choice, int fixed, const std::vector<std::string>& names) {
  return choice == Choice::kPlan ? "plan" : choice == Choice::kRandom ? "random" : "single:" + names[fixed];
}

}  // namespace

nlohmann::json train_value(const ValueRun& a) {
  const fs::path out = a.out;
  fs::create_directories(out);
  const auto data = out / "data.safetensors";
  // The labels are steps to the next boundary capped at the horizon: another horizon, other data.
  const nlohmann::json made = {{"seed", a.seed}, {"scenes", a.episodes}, {"horizon", a.horizon}};
  render_training_data_once(data, made, "value train", [&] {
    ValueDataOptions o;
    o.episodes = a.episodes;
    o.seed = a.seed;
    o.horizon = a.horizon;
    LOG_INFO("value train: rendering ", a.episodes, " labelled demonstrator episodes in DojoSim");
    make_value_data(o, data);
  });
  train::ValueTrainJob job;
  job.data = data;
  job.out = out;
  job.steps = a.steps;
  job.batch_size = static_cast<int>(a.batch);
  job.accumulate = a.accumulate;
  job.horizon = a.horizon;
  const auto r = train::run_value_training(job);
  const nlohmann::json result = {{"steps", r.steps},
                                 {"loss", r.loss},
                                 {"heldout",
                                  {{"windows", r.heldout.windows},
                                   {"mean_abs_steps", r.heldout.mean_abs_steps},
                                   {"order_accuracy", r.heldout.order_accuracy}}},
                                 {"seconds", r.seconds}};
  write_file_atomic(out / "result.json", result.dump(2) + "\n");
  LOG_INFO("value train: held-out windows: ", r.heldout.mean_abs_steps,
           " steps off on average, the closer of ", "two windows valued lower in ", r.heldout.order_accuracy,
           " of pairs");
  return result;
}

nlohmann::json PlanReport::to_json() const {
  nlohmann::json singles = nlohmann::json::object();
  for (size_t i = 0; i < proposers.size(); ++i) singles[proposers[i]] = single[i];
  return {{"proposers", proposers},
          {"plan", plan},
          {"random", random},
          {"best_single", best_single},
          {"best_proposer", best_proposer},
          {"single", singles},
          {"decision_seconds", decision_seconds},
          {"proposals_per_decision", proposals}};
}

PlanReport run_planning(const PlanRun& a) {
  const fs::path out = a.out;
  DOJO_CHECK(a.proposers.size() >= 2, "plan: at least two proposers are needed");
  // The value model's episodes must not be the scenes planned on.
  const fs::path value_dir = a.value.empty() ? out / "value" : fs::path(a.value);
  std::vector<SeedRange> ranges = {{"the planning scenes", a.seed, a.scenes}};
  // data.json lies in the training run's directory, beside its checkpoint.
  if (const auto made = training_data_record(value_dir); !made.empty()) {
    const auto j = read_json_file(made);
    ranges.push_back(
        {"the value model's episodes", j.value("seed", uint64_t{0}), j.value("scenes", int64_t{0})});
  } else if (a.value.empty()) {
    ranges.push_back({"the value model's episodes", a.value_training.seed, a.value_training.episodes});
  }
  check_disjoint_seeds(ranges);
  // What would stop the first decision is refused before the value model trains (minutes).
  DOJO_CHECK(a.options.decide_every > 0 && a.options.proposal_length >= a.options.decide_every,
             "plan: --proposal-length " + std::to_string(a.options.proposal_length) +
                 " must be at least --decide-every " + std::to_string(a.options.decide_every));
  std::vector<std::unique_ptr<Proposer>> owned;
  std::vector<Proposer*> proposers;
  PlanReport report;
  nlohmann::json proposer_paths = nlohmann::json::array();
  for (const auto& dir : a.proposers) {
    const auto name = proposer_name(dir);
    DOJO_CHECK(std::find(report.proposers.begin(), report.proposers.end(), name) == report.proposers.end(),
               "plan: two proposers are named '" + name + "' (" + dir.string() + ")");
    auto policy = models::load_bc_policy(dir);
    DOJO_CHECK(policy->config().chunk >= a.options.proposal_length,
               "plan: " + dir.string() + " predicts " + std::to_string(policy->config().chunk) +
                   " commands at a time, fewer than --proposal-length " +
                   std::to_string(a.options.proposal_length));
    owned.push_back(make_bc_proposer(name, std::move(policy)));
    proposers.push_back(owned.back().get());
    report.proposers.push_back(name);
    proposer_paths.push_back(checkpoint_fingerprint(dir));
  }
  if (a.world_model)
    DOJO_CHECK(a.options.proposal_length % a.world_model->commands_per_step() == 0,
               "plan: --proposal-length " + std::to_string(a.options.proposal_length) +
                   " does not fill the " + (a.world_model->teacher ? "teacher" : "student") + "'s steps of " +
                   std::to_string(a.world_model->commands_per_step()) + " commands");
  fs::create_directories(out);
  if (a.value.empty() &&
      !(fs::exists(value_dir / "result.json") &&
        read_json_file(value_dir / "result.json").value("steps", int64_t{-1}) == a.value_training.steps)) {
    ValueRun v = a.value_training;
    v.out = value_dir.string();
    train_value(v);
  }
  // The world model after the value model trains: training needs the memory more.
  std::optional<LoadedWorldModel> loaded;
  std::unique_ptr<Imagination> imagination;
  if (a.world_model) {
    loaded = load_world_model(*a.world_model, models::SuccessDetector{nullptr});
    imagination = make_world_model_imagination(*loaded->environment);
  } else {
    imagination = make_simulator_imagination();
  }
  DOJO_CHECK(checkpoint_exists(value_dir / "checkpoint") || checkpoint_exists(value_dir),
             "plan: no value model at " + value_dir.string());
  auto scorer = make_value_scorer(models::load_value_model(run_checkpoint(value_dir)));
  PolicySceneOptions scene_options;
  scene_options.count = a.scenes;
  scene_options.seed = a.seed;
  const auto scenes = make_policy_scenes(scene_options);
  const nlohmann::json fingerprint = {
      {"proposers", proposer_paths},
      {"imagination", a.world_model ? a.world_model->fingerprint() : nlohmann::json("dojosim")},
      {"value", checkpoint_fingerprint(value_dir)},
      {"scenes", {{"count", a.scenes}, {"seed", a.seed}}},
      {"options",
       {{"frames", a.options.frames},
        {"settle_frames", a.options.settle_frames},
        {"decide_every", a.options.decide_every},
        {"proposal_length", a.options.proposal_length},
        {"context", a.options.context}}}};
  JsonJournal journal(out / "journal.jsonl", fingerprint, "planning");
  std::map<std::pair<std::string, int64_t>, nlohmann::json> done;
  for (const auto& r : journal.records())
    if (r.contains("mode") && r.contains("scene") && r.contains("episode"))
      done[{r["mode"].get<std::string>(), r["scene"].get<int64_t>()}] = r["episode"];

  std::vector<std::pair<Choice, int>> modes = {{Choice::kPlan, -1}, {Choice::kRandom, -1}};
  for (int k = 0; k < static_cast<int>(proposers.size()); ++k) modes.emplace_back(Choice::kFixed, k);
  const fs::path video_dir = out / "videos";
  eval::HtmlReport html("Planning with a value model: " + imagination->name() + " imagination");
  Progress progress("plan", static_cast<int64_t>(modes.size() * scenes.size()), "episode");
  for (const auto& start : scenes) {
    for (const auto& [choice, fixed] : modes) {
      const auto mode = mode_name(choice, fixed, report.proposers);
      if (!done.count({mode, start.index})) {
        std::vector<torch::Tensor> imagined;
        const bool filmed = choice == Choice::kPlan && start.index < a.videos;
        const auto episode = plan_episode(start, proposers, imagination.get(), scorer.get(), choice, fixed,
                                          a.options, start.seed * 7919 + 17, filmed ? &imagined : nullptr);
        if (filmed && !imagined.empty()) {
          fs::create_directories(video_dir);
          std::vector<torch::Tensor> panels;
          std::vector<std::string> labels;
          for (size_t k = 0; k < imagined.size(); ++k) {
            panels.push_back(io::upscale_nearest(imagined[k], 3));
            labels.push_back(report.proposers[k] + " " + fixed3(episode.values[0][k]));
          }
          io::write_comparison_video(example_video(video_dir, start.index).string(), panels, labels, 10.0);
        }
        const nlohmann::json record = {
            {"mode", mode}, {"scene", start.index}, {"episode", episode.to_json()}};
        journal.append(record);
        done[{mode, start.index}] = record["episode"];
      }
      progress.advance();
    }
  }
  progress.finish();
  // Success rates over the scenes, per mode.
  const auto rate = [&](const std::string& mode) {
    double sum = 0;
    for (const auto& start : scenes) sum += done.at({mode, start.index}).at("success").get<double>();
    return sum / static_cast<double>(scenes.size());
  };
  report.plan = rate("plan");
  report.random = rate("random");
  report.proposals = static_cast<int64_t>(proposers.size());
  for (size_t k = 0; k < proposers.size(); ++k) {
    report.single.push_back(rate("single:" + report.proposers[k]));
    if (report.single.back() > report.best_single || k == 0) {
      report.best_single = report.single.back();
      report.best_proposer = report.proposers[k];
    }
  }
  double decision_seconds = 0;
  int64_t decisions = 0;
  for (const auto& start : scenes) {
    const auto& e = done.at({"plan", start.index});
    decision_seconds += e.at("decision_seconds").get<double>() * e.at("decisions").get<double>();
    decisions += e.at("decisions").get<int64_t>();
  }
  report.decision_seconds = decisions ? decision_seconds / static_cast<double>(decisions) : 0;
  auto json = report.to_json();
  json["imagination"] = imagination->name();
  json["fingerprint"] = fingerprint;
  json["scenes"] = a.scenes;
  write_file_atomic(out / "report.json", json.dump(2) + "\n");

  html.heading("Success over " + std::to_string(a.scenes) + " DojoSim scenes");
  std::vector<std::vector<std::string>> rows = {
      {"planning (" + std::to_string(proposers.size()) + " proposals a decision)", fixed3(report.plan)},
      {"a random proposal each decision", fixed3(report.random)}};
  for (size_t k = 0; k < proposers.size(); ++k)
    rows.push_back({report.proposers[k] + " alone", fixed3(report.single[k])});
  html.table({"how the commands were chosen", "success"}, rows);
  html.paragraph("Mean decision latency (imagining and scoring every proposal): " +
                 fixed3(report.decision_seconds) + " s.");
  bool heading = false;
  for (const auto& start : scenes) {
    const auto mp4 = example_video(video_dir, start.index);
    if (start.index >= a.videos || !fs::exists(mp4)) continue;
    if (!heading) html.heading("Example decisions (the first of each filmed scene)");
    heading = true;
    const auto& e = done.at({"plan", start.index});
    html.video(mp4, "scene " + std::to_string(start.index) +
                        ": each proposal's imagined video with its value (lower wins); chosen: " +
                        report.proposers[e.at("chosen")[0].get<int>()] + "; the episode in DojoSim: " +
                        (e.at("success").get<double>() > 0.5 ? "success" : "failure"));
  }
  html.write(out / "report.html");
  return report;
}

}  // namespace dojo::recipes
