#include "recipes/planning.h"

#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <random>

#include "core/error.h"
#include "recipes/dojosim_policies.h"
#include "sim/task.h"
#include "train/value_train.h"

namespace fs = std::filesystem;

namespace dojo::recipes {
namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

class BcProposer : public Proposer {
 public:
  BcProposer(std::string name, models::BcPolicy policy)
      : name_(std::move(name)), policy_(std::move(policy)) {}
  const std::string& name() const override { return name_; }
  void reset(const eval::EpisodeStart&) override {}
  torch::Tensor propose(const torch::Tensor& frames, const torch::Tensor& last_command, int64_t,
                        int64_t n) override {
    const int64_t chunk = policy_->config().chunk;
    DOJO_CHECK(n <= chunk, "proposer '" + name_ + "': proposals of " + std::to_string(n) +
                               " commands, but the policy predicts " + std::to_string(chunk));
    return models::bc_act(policy_, frames[-1], last_command).narrow(0, 0, n).contiguous();  // [n, A]
  }

 private:
  std::string name_;
  models::BcPolicy policy_;
};

class WorldModelImagination : public Imagination {
 public:
  explicit WorldModelImagination(eval::Environment& world_model) : world_model_(world_model) {}
  std::string name() const override { return world_model_.name(); }
  torch::Tensor imagine(const ImaginationRequest& request, const torch::Tensor& proposal) override {
    eval::EpisodeStart from = *request.start;
    from.frame = request.frame;
    from.command = request.last_command;
    from.seed = request.seed;
    world_model_.reset(from);
    const int64_t per =
        world_model_.actions_per_step() > 0 ? world_model_.actions_per_step() : proposal.size(0);
    DOJO_CHECK(proposal.size(0) % per == 0, "imagination: proposals of " + std::to_string(proposal.size(0)) +
                                                " commands do not fill the world model's steps of " +
                                                std::to_string(per));
    std::vector<torch::Tensor> frames;
    for (int64_t i = 0; i < proposal.size(0); i += per)
      frames.push_back(world_model_.step(proposal.narrow(0, i, per)));
    return torch::cat(frames);  // [n, H, W, 3]
  }

 private:
  eval::Environment& world_model_;
};

class SimulatorImagination : public Imagination {
 public:
  std::string name() const override { return "DojoSim"; }
  torch::Tensor imagine(const ImaginationRequest& request, const torch::Tensor& proposal) override {
    env_.reset(*request.start);
    if (request.executed.defined() && request.executed.size(0) > 0) env_.step(request.executed);
    return env_.step(proposal);
  }

 private:
  DojoSimEnvironment env_;
};

class ValueScorer : public Scorer {
 public:
  explicit ValueScorer(models::ValueModel model) : model_(std::move(model)) {}
  double score(const torch::Tensor& video) override {
    return models::video_value(models::window_values(model_, video));
  }

 private:
  models::ValueModel model_;
};

}  // namespace

void make_value_data(const ValueDataOptions& options, const fs::path& path) {
  DOJO_CHECK(options.episodes > 0 && options.frames > 0 && options.horizon > 0,
             "value data: episodes, frames and horizon must be positive");
  // Demonstrators that carry on toward the bin (retrying a missed grasp): the value is the steps a
  // competent policy still needs from what the frame shows. Policies that idle, wander, drop or
  // misplace on purpose would give the same frames contradicting labels.
  std::vector<PolicySpec> demonstrators;
  for (const auto& spec : default_policy_set())
    if (spec.behavior == "bin_pick" && spec.name != "wrong-place" && spec.name != "drops-half")
      demonstrators.push_back(spec);
  PolicySceneOptions scene_options;
  scene_options.count = options.episodes;
  scene_options.seed = options.seed;
  scene_options.size = options.size;
  const auto scenes = make_policy_scenes(scene_options);
  const auto heldout_from = static_cast<int64_t>(
      std::lround(static_cast<double>(options.episodes) * (1 - options.heldout_fraction)));
  DojoSimEnvironment env;
  std::vector<torch::Tensor> videos, steps;
  std::vector<uint8_t> heldout;
  for (const auto& start : scenes) {
    auto policy = make_scripted_policy(demonstrators[start.index % demonstrators.size()]);
    policy->reset(start);
    std::vector<torch::Tensor> frames{env.reset(start).unsqueeze(0)};
    std::vector<int> stage{sim::bin_task_stage(env.world())};
    auto last = start.command;
    for (int64_t t = 0; t < options.frames + options.settle_frames; ++t) {
      const auto command = t < options.frames ? policy->act(frames.back(), last, 1) : last.unsqueeze(0);
      last = command[0].clone();
      frames.push_back(env.step(command));
      stage.push_back(sim::bin_task_stage(env.world()));
    }
    // Boundaries: the frames at which the highest stage so far rises.
    const int64_t T = static_cast<int64_t>(stage.size());
    std::vector<int64_t> boundaries;
    int reached = stage[0];
    for (int64_t t = 1; t < T; ++t)
      if (stage[t] > reached) {
        reached = stage[t];
        boundaries.push_back(t);
      }
    std::vector<float> to_boundary(T);
    reached = stage[0];
    size_t next = 0;
    for (int64_t t = 0; t < T; ++t) {
      reached = std::max(reached, stage[t]);
      while (next < boundaries.size() && boundaries[next] < t) ++next;
      if (reached >= sim::kBinTaskStages)
        to_boundary[t] = 0;  // done: nothing is closer
      else if (next < boundaries.size())
        to_boundary[t] = static_cast<float>(boundaries[next] - t);
      else
        to_boundary[t] = static_cast<float>(options.horizon);  // no boundary ahead: as far as it gets
    }
    videos.push_back(torch::cat(frames));  // [T, H, W, 3]
    steps.push_back(torch::tensor(to_boundary));
    heldout.push_back(start.index >= heldout_from);
  }
  train::ValueData data;
  data.frames = torch::stack(videos);
  data.steps_to_boundary = torch::stack(steps);
  data.heldout = torch::tensor(std::vector<int64_t>(heldout.begin(), heldout.end())).to(torch::kBool);
  data.save(path);
}

std::unique_ptr<Proposer> make_bc_proposer(std::string name, models::BcPolicy policy) {
  return std::make_unique<BcProposer>(std::move(name), std::move(policy));
}

std::unique_ptr<Imagination> make_world_model_imagination(eval::Environment& world_model) {
  return std::make_unique<WorldModelImagination>(world_model);
}

std::unique_ptr<Imagination> make_simulator_imagination() { return std::make_unique<SimulatorImagination>(); }

std::unique_ptr<Scorer> make_value_scorer(models::ValueModel model) {
  return std::make_unique<ValueScorer>(std::move(model));
}

nlohmann::json PlanEpisode::to_json() const {
  return {{"success", success}, {"decisions", decisions}, {"chosen", chosen},
          {"values", values},   {"seconds", seconds},     {"decision_seconds", decision_seconds}};
}

PlanEpisode plan_episode(const eval::EpisodeStart& start, const std::vector<Proposer*>& proposers,
                         Imagination* imagination, Scorer* scorer, Choice choice, int fixed,
                         const PlanningOptions& options, uint64_t seed,
                         std::vector<torch::Tensor>* imagined) {
  DOJO_CHECK(!proposers.empty(), "planning: no proposers");
  DOJO_CHECK(choice != Choice::kPlan || (imagination && scorer),
             "planning: imagination and a scorer are needed");
  DOJO_CHECK(choice != Choice::kFixed || (fixed >= 0 && fixed < static_cast<int>(proposers.size())),
             "planning: no proposer " + std::to_string(fixed));
  DOJO_CHECK(options.decide_every > 0 && options.proposal_length >= options.decide_every,
             "planning: a proposal must hold at least the commands executed before the next decision");
  const auto t0 = std::chrono::steady_clock::now();
  DojoSimEnvironment env;
  std::vector<torch::Tensor> frames{env.reset(start)};  // [H, W, 3] each
  for (auto* p : proposers) p->reset(start);
  std::mt19937_64 rng(seed);
  PlanEpisode episode;
  auto last = start.command;
  std::vector<torch::Tensor> executed;
  double decision_seconds = 0;
  for (int64_t step = 0; step < options.frames; step += options.decide_every) {
    const auto shown = torch::stack(frames);  // [T, H, W, 3]
    std::vector<torch::Tensor> proposals;
    for (auto* p : proposers) proposals.push_back(p->propose(shown, last, step, options.proposal_length));
    int chosen = fixed;
    if (choice == Choice::kRandom) chosen = static_cast<int>(rng() % proposers.size());
    if (choice == Choice::kPlan) {
      const auto d0 = std::chrono::steady_clock::now();
      ImaginationRequest request;
      request.start = &start;
      request.frame = frames.back();
      request.last_command = last;
      request.executed = executed.empty() ? torch::Tensor() : torch::stack(executed);
      const int64_t context = std::min<int64_t>(options.context, static_cast<int64_t>(frames.size()));
      const auto recent = shown.narrow(0, shown.size(0) - context, context);
      std::vector<double> values;
      for (size_t k = 0; k < proposals.size(); ++k) {
        request.seed = start.seed * 1000003 + static_cast<uint64_t>(step) * 101 + k;
        const auto video = imagination->imagine(request, proposals[k]);  // [n, H, W, 3]
        if (imagined && episode.decisions == 0) imagined->push_back(video);
        values.push_back(scorer->score(torch::cat({recent, video})));
      }
      chosen = static_cast<int>(std::min_element(values.begin(), values.end()) - values.begin());
      episode.values.push_back(values);
      decision_seconds += seconds_since(d0);
    }
    const int64_t n = std::min(options.decide_every, options.frames - step);
    const auto commands = proposals[chosen].narrow(0, 0, n);
    DOJO_CHECK(torch::isfinite(commands).all().item<bool>(),
               "proposer '" + proposers[chosen]->name() + "' proposed non-finite commands");
    const auto new_frames = env.step(commands);
    for (int64_t i = 0; i < n; ++i) {
      frames.push_back(new_frames[i]);
      executed.push_back(commands[i]);
    }
    last = commands[n - 1].clone();
    episode.chosen.push_back(chosen);
    ++episode.decisions;
  }
  for (int64_t i = 0; i < options.settle_frames; ++i) env.step(last.unsqueeze(0));
  episode.success = env.success();
  episode.seconds = seconds_since(t0);
  episode.decision_seconds =
      choice == Choice::kPlan ? decision_seconds / static_cast<double>(episode.decisions) : 0;
  return episode;
}

}  // namespace dojo::recipes
