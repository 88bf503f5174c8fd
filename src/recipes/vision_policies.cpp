#include "recipes/vision_policies.h"

#include <torch/torch.h>

#include <cmath>

#include "core/error.h"
#include "core/stable_hash.h"
#include "models/scene_reader.h"
#include "sim/bin_belief.h"
#include "sim/episode.h"
#include "sim/renderer.h"
#include "sim/skills.h"
#include "sim/world.h"
#include "train/reader_train.h"
#include "train/train_util.h"

namespace fs = std::filesystem;

namespace dojo::recipes {
namespace {

// The robot's control period: DojoSim's rate, which the robot knows as its own (not the scene's).
double control_dt() {
  const sim::SceneSpec defaults;
  return defaults.timestep * defaults.substeps;
}

class ReaderPolicy : public eval::Policy {
 public:
  ReaderPolicy(std::string name, models::SceneReader reader, ReaderKnobs knobs)
      : name_(std::move(name)), reader_(std::move(reader)), knobs_(knobs) {}
  const std::string& name() const override { return name_; }
  void reset(const eval::EpisodeStart& start) override {
    step_ = 0;
    sim::BeliefControllerOptions o;
    o.start_command = command_values(start.command);
    o.control_dt = control_dt();
    o.speed = knobs_.speed;
    o.noise_std = knobs_.noise_std;
    o.max_attempts = knobs_.max_attempts;
    o.seed = start.seed * 1000003 + stable_hash(name_);
    controller_ = std::make_unique<sim::BeliefBinController>(o);
  }
  torch::Tensor act(const torch::Tensor& frames, const torch::Tensor&, int64_t n) override {
    DOJO_CHECK(controller_, "reader policy '" + name_ + "': reset before act");
    std::vector<torch::Tensor> rows;
    for (int64_t i = 0; i < n; ++i) {
      // A plan starts here: read the newest frame shown (only then; in between the plan runs).
      if (controller_->plans_at(step_))
        belief_ = sim::BinBelief::from_values(models::read_scene(reader_, frames[-1]));
      const auto command = controller_->act(belief_, step_++);
      rows.push_back(torch::tensor(std::vector<float>(command.begin(), command.end())));
    }
    return torch::stack(rows);  // [n, 6]
  }

 private:
  std::string name_;
  models::SceneReader reader_;
  ReaderKnobs knobs_;
  std::unique_ptr<sim::BeliefBinController> controller_;
  sim::BinBelief belief_;
  int step_ = 0;
};

}  // namespace

ReaderKnobs ReaderKnobs::from_json(const nlohmann::json& j, const std::string& where) {
  DOJO_CHECK(j.is_object(), where +
                                ": a reader policy's 'quality' must be an object of knobs "
                                "(speed, noise_std, max_attempts)");
  ReaderKnobs k;
  for (const auto& [key, value] : j.items()) {
    DOJO_CHECK(key == "speed" || key == "noise_std" || key == "max_attempts",
               where + ": unknown reader knob '" + key + "' (speed, noise_std, max_attempts)");
    DOJO_CHECK(value.is_number(), where + ": reader knob '" + key + "' must be a number");
  }
  k.speed = j.value("speed", k.speed);
  k.noise_std = j.value("noise_std", k.noise_std);
  if (j.contains("max_attempts")) {
    DOJO_CHECK(j["max_attempts"].is_number_integer(),
               where + ": reader knob 'max_attempts' must be an integer");
    k.max_attempts = j["max_attempts"].get<int>();
  }
  DOJO_CHECK(k.speed > 0.05 && k.speed <= 5, where + ": reader knob 'speed' must be in (0.05, 5]");
  DOJO_CHECK(k.noise_std >= 0 && k.noise_std <= 1, where + ": reader knob 'noise_std' must be in [0, 1]");
  DOJO_CHECK(k.max_attempts >= 1 && k.max_attempts <= 10,
             where + ": reader knob 'max_attempts' must be 1-10");
  return k;
}

nlohmann::json ReaderKnobs::to_json() const {
  return {{"speed", speed}, {"noise_std", noise_std}, {"max_attempts", max_attempts}};
}

std::unique_ptr<eval::Policy> make_reader_policy(const PolicySpec& spec) {
  DOJO_CHECK(!spec.reader.empty(), "policy '" + spec.name + "' is not a reader policy");
  auto reader = models::load_scene_reader(spec.reader);
  DOJO_CHECK(reader->config().outputs == sim::BinBelief::kValues,
             "policy '" + spec.name + "' (" + spec.reader.string() + "): the reader reads " +
                 std::to_string(reader->config().outputs) + " values; the bin belief has " +
                 std::to_string(sim::BinBelief::kValues));
  const auto knobs = ReaderKnobs::from_json(
      spec.quality.is_object() ? spec.quality : nlohmann::json::object(), "policy '" + spec.name + "'");
  return std::make_unique<ReaderPolicy>(spec.name, std::move(reader), knobs);
}

void make_reader_data(const ReaderDataOptions& options, const fs::path& path) {
  DOJO_CHECK(options.episodes > 0 && options.frames > 0 && options.every > 0,
             "reader data: episodes, frames and every must be positive");
  // The demonstrators, in turn: where the object can be seen is what the reader must learn.
  std::vector<PolicySpec> demonstrators;
  for (const auto& s : default_policy_set())
    if (s.behavior == "bin_pick") demonstrators.push_back(s);
  PolicySpec push;
  push.name = "push";
  push.behavior = "push";
  demonstrators.push_back(push);
  PolicySceneOptions scene_options;
  scene_options.count = options.episodes;
  scene_options.seed = options.seed;
  scene_options.size = options.size;
  const auto scenes = make_policy_scenes(scene_options);
  const auto heldout_from = static_cast<int64_t>(
      std::lround(static_cast<double>(options.episodes) * (1 - options.heldout_fraction)));
  sim::Renderer renderer;
  std::vector<torch::Tensor> frames, values;
  std::vector<uint8_t> heldout;
  for (const auto& start : scenes) {
    const auto& spec = demonstrators[start.index % demonstrators.size()];
    sim::World world(sim::scene_from_json(start.scene));
    world.hold(sim::EpisodeSpec{}.settle_steps);
    const auto controller = sim::make_robot_controller(world, scripted_policy_options(spec), start.seed);
    for (int64_t t = 0; t < options.frames; ++t) {
      if (t % options.every == 0) {
        auto rgb = renderer.render(world);
        frames.push_back(
            torch::from_blob(rgb.data(), {world.spec().height, world.spec().width, 3}, torch::kUInt8)
                .clone());
        const auto v = sim::true_bin_belief(world).to_values();
        values.push_back(torch::tensor(std::vector<float>(v.begin(), v.end())));
        heldout.push_back(start.index >= heldout_from);
      }
      world.step(controller->act(world, static_cast<int>(t)));
    }
  }
  train::SceneReadings data;
  data.frames = torch::stack(frames);  // [N, H, W, 3]
  data.values = torch::stack(values);  // [N, 8]
  data.heldout = torch::tensor(std::vector<int64_t>(heldout.begin(), heldout.end())).to(torch::kBool);
  data.save(path);
}

std::vector<PolicySpec> vision_policy_set(const fs::path& bc_dir, const fs::path& reader_dir) {
  std::vector<PolicySpec> specs;
  const auto snapshots = [](const fs::path& dir, const std::string& family, const std::string& how) {
    const auto found = train::list_step_snapshots(dir);
    DOJO_CHECK(!found.empty(),
               dir.string() + ": no " + family + " snapshots (run `" + how + " --out " + dir.string() + "`)");
    return found;
  };
  const auto step_of = [](const fs::path& snapshot) {
    return std::to_string(std::stoll(snapshot.filename().string().substr(5)));
  };
  if (!bc_dir.empty())
    for (const auto& snapshot : snapshots(bc_dir, "policy", "dojo policy train")) {
      PolicySpec s;
      s.name = "bc-" + step_of(snapshot);
      s.checkpoint = snapshot;
      specs.push_back(s);
    }
  if (!reader_dir.empty()) {
    const auto found = snapshots(reader_dir, "reader", "dojo policy reader");
    const auto reader = [&](const std::string& name, const fs::path& snapshot, ReaderKnobs knobs) {
      PolicySpec s;
      s.name = name;
      s.reader = snapshot;
      s.quality = knobs.to_json();
      specs.push_back(s);
    };
    for (const auto& snapshot : found) reader("reader-" + step_of(snapshot), snapshot, {});
    const auto knobs = [](double speed, double noise, int attempts) {
      ReaderKnobs k;
      k.speed = speed;
      k.noise_std = noise;
      k.max_attempts = attempts;
      return k;
    };
    reader("reader-slow", found.back(), knobs(0.6, 0.0, 3));
    reader("reader-hasty", found.back(), knobs(1.8, 0.0, 3));
    reader("reader-noisy", found.back(), knobs(1.0, 0.05, 3));
    reader("reader-very-noisy", found.back(), knobs(1.0, 0.1, 3));
    reader("reader-one-try", found.back(), knobs(1.0, 0.0, 1));
    reader("reader-noisy-one-try", found.back(), knobs(1.0, 0.07, 1));
  }
  return specs;
}

void check_disjoint_seeds(const std::vector<SeedRange>& ranges) {
  for (size_t i = 0; i < ranges.size(); ++i)
    for (size_t j = i + 1; j < ranges.size(); ++j) {
      const auto& a = ranges[i];
      const auto& b = ranges[j];
      if (a.count <= 0 || b.count <= 0) continue;
      const uint64_t a_end = a.first + static_cast<uint64_t>(a.count),
                     b_end = b.first + static_cast<uint64_t>(b.count);
      DOJO_CHECK(a_end <= b.first || b_end <= a.first,
                 a.what + " (seeds " + std::to_string(a.first) + "-" + std::to_string(a_end - 1) + ") and " +
                     b.what + " (seeds " + std::to_string(b.first) + "-" + std::to_string(b_end - 1) +
                     ") share scenes: held-out evaluation needs them apart (change --seed or --scenes)");
    }
}

}  // namespace dojo::recipes
