#include "recipes/dojosim_policies.h"

#include <torch/torch.h>

#include <cmath>
#include <random>
#include <set>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "core/stable_hash.h"
#include "recipes/vision_policies.h"
#include "sim/episode.h"
#include "sim/renderer.h"
#include "sim/skills.h"
#include "sim/task.h"
#include "sim/world.h"
#include "train/bc_train.h"
#include "train/success_train.h"

namespace fs = std::filesystem;

namespace dojo::recipes {
namespace {

sim::SceneSpec policy_scene(uint64_t seed, int size) {
  sim::SceneSampling sampling;
  sampling.min_objects = sampling.max_objects = 1;  // one object: an episode succeeds or fails
  sampling.bin_probability = 1.0;
  sampling.width = sampling.height = size;
  return sim::sample_scene(sim::Embodiment::kRobot, sampling, seed);
}

torch::Tensor to_frame(std::vector<uint8_t> rgb, int height, int width) {
  return torch::from_blob(rgb.data(), {height, width, 3}, torch::kUInt8).clone();  // [H, W, 3]
}

torch::Tensor to_tensor(const std::vector<double>& v) {
  return torch::tensor(std::vector<float>(v.begin(), v.end()), torch::kFloat32);
}

// The world at frame 0 of a scene.
std::unique_ptr<sim::World> start_world(const eval::EpisodeStart& start) {
  auto world = std::make_unique<sim::World>(sim::scene_from_json(start.scene));
  world->hold(sim::EpisodeSpec{}.settle_steps);  // as the generated datasets
  return world;
}

class ScriptedPolicy : public eval::Policy {
 public:
  explicit ScriptedPolicy(PolicySpec spec)
      : spec_(std::move(spec)), options_(scripted_policy_options(spec_)) {}
  const std::string& name() const override { return spec_.name; }
  bool open_loop() const override { return true; }
  void reset(const eval::EpisodeStart& start) override {
    step_ = 0;
    world_ = start_world(start);
    // Each policy draws its own randomness per scene.
    controller_ =
        sim::make_robot_controller(*world_, options_, start.seed * 1000003 + stable_hash(spec_.name));
  }
  torch::Tensor act(const torch::Tensor&, const torch::Tensor&, int64_t n) override {
    std::vector<torch::Tensor> rows;
    for (int64_t i = 0; i < n; ++i) {
      const auto command = controller_->act(*world_, step_++);
      world_->step(command);  // the plan's own copy of the scene follows its commands
      rows.push_back(to_tensor(command));
    }
    return torch::stack(rows);  // [n, 6]
  }

 private:
  PolicySpec spec_;
  sim::RobotPolicyOptions options_;
  std::unique_ptr<sim::World> world_;
  std::unique_ptr<sim::Controller> controller_;
  int step_ = 0;
};

}  // namespace

std::vector<eval::EpisodeStart> make_policy_scenes(const PolicySceneOptions& options) {
  DOJO_CHECK(options.count > 0, "policy scenes: the count must be positive");
  sim::Renderer renderer;
  std::vector<eval::EpisodeStart> scenes;
  for (int64_t i = 0; i < options.count; ++i) {
    eval::EpisodeStart s;
    s.index = i;
    s.seed = options.seed + static_cast<uint64_t>(i);
    const auto spec = policy_scene(s.seed, options.size);
    s.scene = sim::to_json(spec);
    const auto world = start_world(s);
    s.frame = to_frame(renderer.render(*world), spec.height, spec.width);
    s.command = to_tensor(world->last_command());
    scenes.push_back(std::move(s));
  }
  return scenes;
}

DojoSimEnvironment::DojoSimEnvironment() : renderer_(std::make_unique<sim::Renderer>()) {}
DojoSimEnvironment::~DojoSimEnvironment() = default;

torch::Tensor DojoSimEnvironment::reset(const eval::EpisodeStart& start) {
  world_ = start_world(start);
  return to_frame(renderer_->render(*world_), world_->spec().height, world_->spec().width);
}

torch::Tensor DojoSimEnvironment::step(const torch::Tensor& commands) {
  DOJO_CHECK(world_, "DojoSim: reset before step");
  DOJO_CHECK(commands.dim() == 2 && commands.size(1) == world_->action_dim(),
             "DojoSim: commands must be [n, " + std::to_string(world_->action_dim()) + "]");
  std::vector<torch::Tensor> frames;
  for (int64_t i = 0; i < commands.size(0); ++i) {
    world_->step(command_values(commands[i]));
    frames.push_back(to_frame(renderer_->render(*world_), world_->spec().height, world_->spec().width));
  }
  return torch::stack(frames);  // [n, H, W, 3]
}

double DojoSimEnvironment::success() { return success_now(); }

double DojoSimEnvironment::success_now() const {
  DOJO_CHECK(world_, "DojoSim: reset before asking for success");
  return sim::bin_success(*world_);
}

sim::RobotPolicyOptions scripted_policy_options(const PolicySpec& spec) {
  DOJO_CHECK(spec.scripted(), "policy '" + spec.name + "' is not a scripted one");
  sim::RobotPolicyOptions options;
  options.behavior = sim::parse_robot_behavior(spec.behavior);
  options.quality = sim::PolicyQuality::from_json(spec.quality, "policy '" + spec.name + "'");
  return options;
}

std::unique_ptr<eval::Policy> make_scripted_policy(const PolicySpec& spec) {
  DOJO_CHECK(!spec.name.empty(), "scripted policy: a name is needed");
  return std::make_unique<ScriptedPolicy>(spec);  // scripted_policy_options refuses a non-scripted spec
}

std::vector<double> command_values(const torch::Tensor& row) {
  const auto r = row.to(torch::kFloat64).contiguous();
  return std::vector<double>(r.data_ptr<double>(), r.data_ptr<double>() + r.numel());
}

std::vector<PolicySpec> default_policy_set() {
  // JSON values, not doubles: delay_steps must stay an integer to read back.
  const auto knobs = [](std::initializer_list<std::pair<const std::string, nlohmann::json>> k) {
    nlohmann::json j = nlohmann::json::object();
    for (const auto& [key, value] : k) j[key] = value;
    return j;
  };
  const auto scripted = [](const char* name, const char* behavior, nlohmann::json quality) {
    PolicySpec spec;
    spec.name = name;
    spec.behavior = behavior;
    spec.quality = std::move(quality);
    return spec;
  };
  return {
      scripted("expert", "bin_pick", "expert"),
      scripted("good", "bin_pick", "good"),
      scripted("medium", "bin_pick", "medium"),
      scripted("poor", "bin_pick", "poor"),
      scripted("slow", "bin_pick", knobs({{"speed", 0.6}})),
      scripted("noisy", "bin_pick", knobs({{"noise_std", 0.05}})),
      scripted("very-noisy", "bin_pick", knobs({{"noise_std", 0.1}})),
      scripted("late", "bin_pick", knobs({{"delay_steps", 3}, {"noise_std", 0.02}})),
      scripted("misses-half", "bin_pick", knobs({{"miss_prob", 0.5}})),
      scripted("drops-half", "bin_pick", knobs({{"early_release_prob", 0.5}})),
      scripted("wrong-place", "bin_pick", knobs({{"wrong_target_prob", 0.8}})),
      scripted("random", "random_motion", "expert"),
      scripted("idle", "idle", "expert"),
  };
}

std::vector<PolicySpec> read_policy_set(const fs::path& path) {
  const auto j = read_json_file(path);
  DOJO_CHECK(j.is_object() && j.contains("policies") && j["policies"].is_array() && !j["policies"].empty(),
             path.string() +
                 ": expected {\"policies\": [{\"name\": ..., \"behavior\": ..., \"quality\": ...}, ...]}");
  std::vector<PolicySpec> out;
  std::set<std::string> names;
  for (size_t i = 0; i < j["policies"].size(); ++i) {
    const auto& p = j["policies"][i];
    const auto where = path.string() + ": policies[" + std::to_string(i) + "]";
    DOJO_CHECK(
        p.is_object() && p.contains("name") && p["name"].is_string() && !p["name"].get<std::string>().empty(),
        where + ": needs a non-empty string 'name'");
    PolicySpec s;
    s.name = p["name"].get<std::string>();
    DOJO_CHECK(names.insert(s.name).second, where + ": the name '" + s.name + "' is used twice");
    const bool reader = p.contains("reader");
    const int kinds = p.contains("checkpoint") + p.contains("command") + reader +
                      (!reader && (p.contains("behavior") || p.contains("quality")));
    DOJO_CHECK(kinds <= 1 && !(reader && p.contains("behavior")),
               where +
                   ": give one of 'behavior'/'quality' (scripted), 'checkpoint' (learned), 'reader' "
                   "(+ 'quality': a reader policy) or 'command' (external)");
    for (const char* key : {"behavior", "checkpoint", "command", "reader"})
      DOJO_CHECK(!p.contains(key) || (p[key].is_string() && !p[key].get<std::string>().empty()),
                 where + ": '" + key + "' must be a non-empty string");
    for (const auto& [key, value] : p.items())
      DOJO_CHECK(key == "name" || key == "behavior" || key == "quality" || key == "checkpoint" ||
                     key == "command" || key == "reader",
                 where + ": unknown field '" + key + "'");
    if (p.contains("behavior")) s.behavior = p["behavior"].get<std::string>();
    if (p.contains("quality")) s.quality = p["quality"];
    if (p.contains("command")) s.command = p["command"].get<std::string>();
    for (auto [key, field] :
         {std::pair<const char*, fs::path*>{"checkpoint", &s.checkpoint}, {"reader", &s.reader}}) {
      if (!p.contains(key)) continue;
      *field = p[key].get<std::string>();
      if (field->is_relative()) *field = path.parent_path() / *field;
      DOJO_CHECK(checkpoint_exists(*field), where + ": no checkpoint at " + field->string());
    }
    if (reader) {
      if (!p.contains("quality")) s.quality = nlohmann::json::object();
      ReaderKnobs::from_json(s.quality, where + " ('" + s.name + "')");
    }
    if (s.scripted()) {
      try {
        make_scripted_policy(s);  // checks the behaviour and the knobs
      } catch (const std::exception& e) {
        throw Error(where + " ('" + s.name + "'): " + e.what());
      }
    }
    out.push_back(std::move(s));
  }
  return out;
}

void make_success_data(const std::vector<PolicySpec>& policies, const SuccessDataOptions& options,
                       const fs::path& path, eval::Environment* frames_from) {
  DOJO_CHECK(!policies.empty() && options.scenes > 0, "success data: policies and scenes are needed");
  PolicySceneOptions scene_options;
  scene_options.count = options.scenes;
  scene_options.seed = options.seed;
  scene_options.size = options.size;
  const auto scenes = make_policy_scenes(scene_options);
  // A world model's own step size wins, as in run_policy_episode.
  const int64_t n = frames_from && frames_from->actions_per_step() > 0 ? frames_from->actions_per_step()
                                                                       : options.episode.actions_per_step;
  const int64_t steps = options.episode.steps + options.episode.settle_steps;
  const auto heldout_from =
      static_cast<int64_t>(std::lround(static_cast<double>(options.scenes) * (1 - options.heldout_fraction)));
  DojoSimEnvironment env;
  std::vector<torch::Tensor> videos, simulator_videos, labels;
  std::vector<uint8_t> heldout;
  for (const auto& spec : policies) {
    if (!spec.scripted()) continue;  // labelled episodes come from the scripted policies
    auto policy = make_scripted_policy(spec);
    for (const auto& start : scenes) {
      std::vector<torch::Tensor> frames{env.reset(start).unsqueeze(0)};  // the simulator's
      std::vector<torch::Tensor> shown;  // the world model's, when it supplies the frames
      if (frames_from) shown.push_back(frames_from->reset(start).unsqueeze(0));
      std::vector<float> label{static_cast<float>(env.success_now() > 0.5)};
      policy->reset(start);
      auto last = start.command;
      for (int64_t k = 0; k < steps; ++k) {
        const auto commands = k < options.episode.steps ? policy->act(frames.back(), last, n)
                                                        : last.unsqueeze(0).expand({n, -1}).contiguous();
        last = commands[-1].clone();
        // Step one command at a time so every frame gets the label of its own state.
        for (int64_t i = 0; i < n; ++i) {
          frames.push_back(env.step(commands.narrow(0, i, 1)));
          label.push_back(static_cast<float>(env.success_now() > 0.5));
        }
        if (frames_from) shown.push_back(frames_from->step(commands));  // [n, H, W, 3]
      }
      videos.push_back(torch::cat(frames_from ? shown : frames));  // [T, H, W, 3]
      if (frames_from) simulator_videos.push_back(torch::cat(frames));
      DOJO_CHECK(videos.back().size(0) == static_cast<int64_t>(label.size()),
                 "success data: " + (frames_from ? frames_from->name() : env.name()) + " returned " +
                     std::to_string(videos.back().size(0)) + " frames for " + std::to_string(label.size()) +
                     " labelled ones");
      labels.push_back(torch::tensor(label));
      heldout.push_back(start.index >= heldout_from);
    }
    LOG_INFO("success data: ", spec.name, " done");
  }
  train::SuccessData data;
  data.frames = torch::stack(videos);                                       // [E, T, H, W, 3]
  data.labels = torch::stack(labels);                                       // [E, T]
  if (frames_from) data.simulator_frames = torch::stack(simulator_videos);  // [E, T, H, W, 3]
  data.heldout = torch::tensor(std::vector<int64_t>(heldout.begin(), heldout.end())).to(torch::kBool);
  data.save(path);
}

void make_demonstrations(const DemonstrationOptions& options, const fs::path& path) {
  DOJO_CHECK(options.episodes > 0 && options.frames > 0,
             "demonstrations: episodes and frames must be positive");
  sim::Renderer renderer;
  sim::RobotPolicyOptions expert;
  expert.quality = sim::PolicyQuality::preset("expert");
  const auto heldout_from = static_cast<int64_t>(
      std::lround(static_cast<double>(options.episodes) * (1 - options.heldout_fraction)));
  constexpr double kNoiseMemory = 0.8;  // AR(1): noise that drifts over a few steps, like a real error
  std::vector<torch::Tensor> videos, executed, labels;
  std::vector<uint8_t> heldout;
  for (int64_t e = 0; e < options.episodes; ++e) {
    eval::EpisodeStart start;
    start.seed = options.seed + static_cast<uint64_t>(e);
    start.scene = sim::to_json(policy_scene(start.seed, options.size));
    auto world = start_world(start);
    const auto controller = sim::make_robot_controller(*world, expert, start.seed);
    std::mt19937_64 rng(start.seed ^ 0x5eedda27ull);
    std::normal_distribution<double> normal(0.0,
                                            options.noise_std * std::sqrt(1 - kNoiseMemory * kNoiseMemory));
    std::vector<double> noise(world->action_dim(), 0.0);
    std::vector<torch::Tensor> frames, in_force, said;
    for (int64_t t = 0; t < options.frames; ++t) {
      frames.push_back(to_frame(renderer.render(*world), world->spec().height, world->spec().width));
      in_force.push_back(to_tensor(world->last_command()));
      auto command = controller->act(*world, static_cast<int>(t));
      said.push_back(to_tensor(command));
      for (size_t j = 0; j + 1 < command.size(); ++j) {  // the arm's joints; the gripper stays as told
        noise[j] = options.noise_std > 0 ? kNoiseMemory * noise[j] + normal(rng) : 0.0;
        command[j] += noise[j];
      }
      world->step(command);
    }
    videos.push_back(torch::stack(frames));  // [T, H, W, 3]
    executed.push_back(torch::stack(in_force));
    labels.push_back(torch::stack(said));
    heldout.push_back(e >= heldout_from);
  }
  train::Demonstrations data;
  data.frames = torch::stack(videos);      // [E, T, H, W, 3]
  data.executed = torch::stack(executed);  // [E, T, A]
  data.labels = torch::stack(labels);      // [E, T, A]
  data.heldout = torch::tensor(std::vector<int64_t>(heldout.begin(), heldout.end())).to(torch::kBool);
  data.save(path);
}

}  // namespace dojo::recipes
