#include "eval/policy_eval.h"

#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <optional>
#include <set>

#include "core/error.h"
#include "core/json_file.h"
#include "core/json_journal.h"
#include "core/log.h"
#include "core/timing.h"
#include "eval/html_report.h"
#include "infer/generator.h"
#include "io/video.h"

namespace fs = std::filesystem;

namespace dojo::eval {

// ------------------------------------------------------------------------------------------------
// The world model as an environment

WorldModelEnvironment::WorldModelEnvironment(std::string name, std::unique_ptr<infer::Generator> generator,
                                             data::ActionChunker chunker, models::SuccessDetector detector,
                                             int64_t votes)
    : name_(std::move(name)),
      generator_(std::move(generator)),
      chunker_(std::move(chunker)),
      detector_(std::move(detector)),
      votes_(votes) {
  DOJO_CHECK(generator_, "world-model environment: a generator is needed");
}

WorldModelEnvironment::~WorldModelEnvironment() = default;

int64_t WorldModelEnvironment::actions_per_step() const { return generator_->actions_per_step(); }

torch::Tensor WorldModelEnvironment::reset(const EpisodeStart& start) {
  DOJO_CHECK(start.command.defined() && start.command.numel() == chunker_.width(),
             name_ + ": the start command has " +
                 std::to_string(start.command.defined() ? start.command.numel() : 0) +
                 " values; the model's actions have " + std::to_string(chunker_.width()));
  chunker_.reset();
  chunker_.set_baseline(start.command.to(torch::kFloat32));
  frames_.clear();
  frames_.push_back(generator_->reset(start.frame, start.seed));  // [1, H, W, 3]
  return frames_.back()[-1];
}

torch::Tensor WorldModelEnvironment::step(const torch::Tensor& commands) {
  DOJO_CHECK(commands.dim() == 2 && commands.size(0) == generator_->actions_per_step(),
             name_ + ": a step takes " + std::to_string(generator_->actions_per_step()) + " commands");
  const auto rows = chunker_.push(commands.to(torch::kFloat32));  // [n, 384]
  frames_.push_back(generator_->step(rows));                      // [n, H, W, 3]
  return frames_.back();
}

double WorldModelEnvironment::success() {
  DOJO_CHECK(detector_, name_ + ": no success detector to read the outcome with");
  return models::success_vote(detector_, video(), votes_) > 0.5 ? 1.0 : 0.0;
}

torch::Tensor WorldModelEnvironment::video() const { return torch::cat(frames_); }

// ------------------------------------------------------------------------------------------------
// The behaviour-cloning policy

namespace {

class BcPolicyAdapter : public Policy {
 public:
  BcPolicyAdapter(std::string name, models::BcPolicy policy)
      : name_(std::move(name)), policy_(std::move(policy)) {}
  const std::string& name() const override { return name_; }
  void reset(const EpisodeStart&) override {}
  torch::Tensor act(const torch::Tensor& frames, const torch::Tensor& last_command, int64_t n) override {
    std::vector<torch::Tensor> chunks;
    int64_t have = 0;
    auto last = last_command;
    while (have < n) {
      const auto chunk = models::bc_act(policy_, frames[-1], last);  // [chunk, w]
      chunks.push_back(chunk);
      have += chunk.size(0);
      last = chunk[-1];
    }
    return torch::cat(chunks).narrow(0, 0, n);  // [n, w]
  }

 private:
  std::string name_;
  models::BcPolicy policy_;
};

}  // namespace

std::unique_ptr<Policy> make_bc_policy(std::string name, models::BcPolicy policy) {
  return std::make_unique<BcPolicyAdapter>(std::move(name), std::move(policy));
}

// ------------------------------------------------------------------------------------------------
// Episodes

double run_policy_episode(Policy& policy, Environment& env, const EpisodeStart& start,
                          const PolicyEvalOptions& options, std::vector<torch::Tensor>* shown) {
  const int64_t n = env.actions_per_step() > 0 ? env.actions_per_step() : options.actions_per_step;
  const int64_t width = start.command.numel();
  auto frames = env.reset(start).unsqueeze(0);  // [1, H, W, 3]
  if (shown) shown->push_back(frames);
  policy.reset(start);
  auto last = start.command.to(torch::kFloat32);
  for (int64_t k = 0; k < options.steps; ++k) {
    const auto commands = policy.act(frames, last, n);
    DOJO_CHECK(
        commands.defined() && commands.dim() == 2 && commands.size(0) == n && commands.size(1) == width,
        "policy '" + policy.name() + "': expected " + std::to_string(n) + " commands of width " +
            std::to_string(width) + " (the environment's action space), got " +
            (commands.defined() ? "[" + std::to_string(commands.size(0)) + ", " +
                                      std::to_string(commands.dim() > 1 ? commands.size(1) : 0) + "]"
                                : std::string("none")));
    const auto rows = commands.to(torch::kFloat32);
    DOJO_CHECK(torch::isfinite(rows).all().item<bool>(),
               "policy '" + policy.name() + "': non-finite command");
    frames = env.step(rows);  // [n, H, W, 3]
    if (shown) shown->push_back(frames);
    last = rows[-1];
  }
  const auto hold = last.unsqueeze(0).expand({n, width}).contiguous();
  for (int64_t k = 0; k < options.settle_steps; ++k) {
    const auto settled = env.step(hold);
    if (shown) shown->push_back(settled);
  }
  return env.success();
}

nlohmann::json EpisodeResult::to_json() const {
  return {{"policy", policy},
          {"scene", scene},
          {"real", real},
          {"world_model", world_model},
          {"real_seconds", real_seconds},
          {"world_model_seconds", world_model_seconds},
          {"open_loop", open_loop}};
}

EpisodeResult EpisodeResult::from_json(const nlohmann::json& j) {
  EpisodeResult r;
  r.policy = j.at("policy").get<std::string>();
  r.scene = j.at("scene").get<int64_t>();
  r.real = j.at("real").get<double>();
  r.world_model = j.at("world_model").get<double>();
  r.real_seconds = j.value("real_seconds", 0.0);
  r.world_model_seconds = j.value("world_model_seconds", 0.0);
  r.open_loop = j.value("open_loop", false);
  return r;
}

PolicyRates rates_of(const PolicyRates& rates, const std::vector<std::string>& names) {
  PolicyRates out;
  for (size_t i = 0; i < rates.names.size(); ++i) {
    if (std::find(names.begin(), names.end(), rates.names[i]) == names.end()) continue;
    out.names.push_back(rates.names[i]);
    out.world_model.push_back(rates.world_model[i]);
    out.real.push_back(rates.real[i]);
  }
  return out;
}

PolicyEvalReport summarize_policy_episodes(const std::vector<EpisodeResult>& episodes) {
  PolicyEvalReport report;
  report.episodes = episodes;
  std::map<std::string, std::pair<double, double>> sums;
  std::map<std::string, int64_t> counts;
  int64_t agree = 0, open = 0, open_agree = 0;
  for (const auto& e : episodes) {
    if (!counts.count(e.policy)) report.rates.names.push_back(e.policy);
    sums[e.policy].first += e.world_model;
    sums[e.policy].second += e.real;
    ++counts[e.policy];
    const bool same = (e.world_model > 0.5) == (e.real > 0.5);
    agree += same;
    open += e.open_loop;
    open_agree += e.open_loop && same;
    report.real_seconds_per_episode += e.real_seconds;
    report.world_model_seconds_per_episode += e.world_model_seconds;
  }
  for (const auto& name : report.rates.names) {
    report.rates.world_model.push_back(sums[name].first / static_cast<double>(counts[name]));
    report.rates.real.push_back(sums[name].second / static_cast<double>(counts[name]));
  }
  if (!episodes.empty()) {
    const auto n = static_cast<double>(episodes.size());
    report.episode_agreement = static_cast<double>(agree) / n;
    report.real_seconds_per_episode /= n;
    report.world_model_seconds_per_episode /= n;
  }
  report.open_loop_agreement =
      open ? static_cast<double>(open_agree) / static_cast<double>(open) : std::nan("");
  if (report.rates.names.size() >= 2) report.agreement = policy_agreement(report.rates);
  return report;
}

nlohmann::json PolicyEvalReport::to_json() const {
  nlohmann::json policies = nlohmann::json::array();
  for (size_t i = 0; i < rates.names.size(); ++i)
    policies.push_back(
        {{"name", rates.names[i]}, {"world_model", rates.world_model[i]}, {"real", rates.real[i]}});
  nlohmann::json eps = nlohmann::json::array();
  for (const auto& e : episodes) eps.push_back(e.to_json());
  return {{"policies", policies},
          {"agreement", agreement.to_json()},
          {"episode_agreement", finite_or_null(episode_agreement)},
          {"open_loop_agreement", finite_or_null(open_loop_agreement)},
          {"seconds_per_episode",
           {{"real", real_seconds_per_episode}, {"world_model", world_model_seconds_per_episode}}},
          {"episodes", eps}};
}

namespace {

std::string outcome(double success) { return success > 0.5 ? "success" : "failure"; }

fs::path episode_video(const fs::path& dir, const std::string& policy, int64_t scene) {
  return dir / (policy + "-scene-" + std::to_string(scene) + ".mp4");
}

void write_episode_video(const fs::path& dir, const EpisodeResult& r, const std::string& real_name,
                         const std::string& world_model_name, const std::vector<torch::Tensor>& real_frames,
                         const std::vector<torch::Tensor>& world_model_frames) {
  fs::create_directories(dir);
  constexpr int64_t kEnlarge = 4;
  io::write_comparison_video(
      episode_video(dir, r.policy, r.scene).string(),
      {io::upscale_nearest(torch::cat(real_frames), kEnlarge),
       io::upscale_nearest(torch::cat(world_model_frames), kEnlarge)},
      {real_name + ": " + outcome(r.real), world_model_name + ": " + outcome(r.world_model)}, 10.0);
}

}  // namespace

PolicyEvalReport evaluate_policies(const std::vector<Policy*>& policies,
                                   const std::vector<EpisodeStart>& scenes, Environment& real,
                                   Environment& world_model, const PolicyEvalOptions& options,
                                   const fs::path& journal, const nlohmann::json& fingerprint,
                                   const std::function<void(int64_t, int64_t)>& on_episode) {
  DOJO_CHECK(policies.size() >= 2, "policy eval: at least two policies are needed to compare rankings");
  DOJO_CHECK(!scenes.empty(), "policy eval: no scenes");
  std::set<std::string> names;
  for (const auto* p : policies)
    DOJO_CHECK(names.insert(p->name()).second, "policy eval: two policies are named '" + p->name() + "'");
  std::vector<EpisodeResult> results;
  std::set<std::pair<std::string, int64_t>> finished;
  std::optional<JsonJournal> out;
  if (!journal.empty()) {
    out.emplace(journal, fingerprint, "policy evaluation");
    for (const auto& record : out->records()) {
      EpisodeResult r;
      try {
        r = EpisodeResult::from_json(record);
      } catch (const std::exception& e) {
        LOG_WARN(journal.string(), ": skipped an unreadable episode (", e.what(), ")");  // it is rerun
        continue;
      }
      if (names.count(r.policy) && finished.insert({r.policy, r.scene}).second)
        results.push_back(std::move(r));
    }
  }
  const int64_t total = static_cast<int64_t>(policies.size() * scenes.size());
  int64_t done = static_cast<int64_t>(results.size());
  for (auto* policy : policies) {
    for (const auto& start : scenes) {
      if (finished.count({policy->name(), start.index})) continue;
      EpisodeResult r;
      r.policy = policy->name();
      r.scene = start.index;
      r.open_loop = policy->open_loop();
      const bool filmed = start.index < options.videos && !options.video_dir.empty();
      std::vector<torch::Tensor> real_frames, world_model_frames;
      auto t0 = std::chrono::steady_clock::now();
      r.real = run_policy_episode(*policy, real, start, options, filmed ? &real_frames : nullptr);
      r.real_seconds = seconds_since(t0);
      t0 = std::chrono::steady_clock::now();
      r.world_model =
          run_policy_episode(*policy, world_model, start, options, filmed ? &world_model_frames : nullptr);
      r.world_model_seconds = seconds_since(t0);
      if (filmed)
        write_episode_video(options.video_dir, r, real.name(), world_model.name(), real_frames,
                            world_model_frames);
      if (out) out->append(r.to_json());
      results.push_back(r);
      if (on_episode) on_episode(++done, total);
    }
    policy->finish();
  }
  // Report in the order of `policies`, whatever order the journal held them in.
  std::vector<EpisodeResult> ordered;
  for (const auto* p : policies)
    for (const auto& r : results)
      if (r.policy == p->name()) ordered.push_back(r);
  return summarize_policy_episodes(ordered);
}

void write_policy_eval_html(const PolicyEvalReport& report, const fs::path& path,
                            const std::string& real_name, const std::string& world_model_name,
                            const fs::path& video_dir, const std::string& detector_note) {
  const auto f = [](double v, int digits = 3) {
    if (!std::isfinite(v)) return std::string("—");
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.*f", digits, v);
    return std::string(buf);
  };
  HtmlReport html("Policy evaluation: " + world_model_name + " vs " + real_name);
  html.heading("Agreement");
  html.table(
      {"Pearson r", "MMRV", "Spearman ρ", "mean |gap|", "episodes agreeing", "open-loop replays agreeing"},
      {{f(report.agreement.pearson), f(report.agreement.mmrv), f(report.agreement.spearman),
        f(report.agreement.mean_abs_gap), f(report.episode_agreement), f(report.open_loop_agreement)}});
  html.paragraph("Seconds per episode: " + f(report.real_seconds_per_episode, 2) + " in " + real_name + ", " +
                 f(report.world_model_seconds_per_episode, 2) + " in " + world_model_name + ".");
  if (!detector_note.empty()) html.paragraph(detector_note + ".");
  html.unit_scatter("Success rate per policy", report.rates.names, report.rates.real,
                    report.rates.world_model, "success in " + real_name, "success in " + world_model_name);
  std::vector<std::vector<std::string>> rows;
  for (size_t i = 0; i < report.rates.names.size(); ++i)
    rows.push_back({report.rates.names[i], f(report.rates.real[i]), f(report.rates.world_model[i])});
  html.heading("Policies");
  html.table({"policy", real_name, world_model_name}, rows);
  bool heading = false;
  for (const auto& e : report.episodes) {
    const auto mp4 = episode_video(video_dir, e.policy, e.scene);
    if (video_dir.empty() || !fs::exists(mp4)) continue;
    if (!heading) html.heading("Episodes: " + real_name + " | " + world_model_name);
    heading = true;
    html.video(mp4, e.policy + ", scene " + std::to_string(e.scene) + ": " + outcome(e.real) + " in " +
                        real_name + ", " + outcome(e.world_model) + " in " + world_model_name);
  }
  html.write(path);
}

}  // namespace dojo::eval
