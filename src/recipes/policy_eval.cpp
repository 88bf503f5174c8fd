#include "recipes/policy_eval.h"

#include <torch/torch.h>

#include <algorithm>
#include <cstdio>
#include <optional>

#include "core/atomic_file.h"
#include "core/autocast.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "core/progress.h"
#include "core/runtime.h"
#include "infer/generator.h"
#include "infer/streaming.h"
#include "infer/world_model.h"
#include "models/bc_policy.h"
#include "models/fast_decoder.h"
#include "recipes/dojosim_policies.h"
#include "recipes/vision_policies.h"
#include "train/bc_train.h"
#include "train/data_parallel.h"
#include "train/reader_train.h"
#include "train/success_train.h"
#include "train/train_util.h"

namespace fs = std::filesystem;

namespace dojo::recipes {
namespace {

// The policies a detector learns from: the set `file` names, or the demonstrators when it names
// none (or none scripted: labelled episodes need scripted policies).
std::vector<PolicySpec> detector_training_set(const std::string& file) {
  auto specs = file.empty() ? default_policy_set() : read_policy_set(file);
  if (std::none_of(specs.begin(), specs.end(), [](const auto& s) { return s.scripted(); }))
    specs = default_policy_set();
  return specs;
}

// The policy a spec names. DojoSim's robot takes 6-value commands; a learned policy of another
// width is refused here, before any episode runs.
std::unique_ptr<eval::Policy> make_policy(const PolicySpec& spec, int64_t command_width,
                                          const PolicyEvalRun& run) {
  if (!spec.checkpoint.empty()) {
    auto model = models::load_bc_policy(spec.checkpoint);
    DOJO_CHECK(model->config().action_dim == command_width,
               "policy '" + spec.name + "' (" + spec.checkpoint.string() + "): its commands have " +
                   std::to_string(model->config().action_dim) + " values; the robot takes " +
                   std::to_string(command_width));
    return eval::make_bc_policy(spec.name, std::move(model));
  }
  if (!spec.reader.empty()) return make_reader_policy(spec);
  if (!spec.command.empty()) {
    DOJO_CHECK(run.make_external, "policy '" + spec.name + "': external policies are not available here");
    return run.make_external(spec);
  }
  return make_scripted_policy(spec);
}

// NAME=COMMAND
PolicySpec external_spec(const std::string& text) {
  const auto eq = text.find('=');
  DOJO_CHECK(eq != std::string::npos && eq > 0 && eq + 1 < text.size(),
             "--external: expected NAME=COMMAND, got '" + text + "'");
  PolicySpec s;
  s.name = text.substr(0, eq);
  s.command = text.substr(eq + 1);
  return s;
}

eval::PolicyEvalOptions episode_options(int64_t frames, int64_t settle_frames, int64_t per_step) {
  DOJO_CHECK(frames > 0 && settle_frames >= 0, "policy: --frames must be positive and --settle-frames >= 0");
  eval::PolicyEvalOptions o;
  o.actions_per_step = per_step;
  o.steps = (frames + per_step - 1) / per_step;
  o.settle_steps = (settle_frames + per_step - 1) / per_step;
  return o;
}

fs::path pick(const std::string& given, const fs::path& fallback) {
  return given.empty() ? fallback : fs::path(given);
}

// The frames a detector directory's data holds: data.json's "frames"; an older directory without
// data.json holds DojoSim's.
nlohmann::json detector_frames_in(const fs::path& dir) {
  const auto record = training_data_record(dir);
  return record.empty() ? nlohmann::json("dojosim")
                        : read_json_file(record).value("frames", nlohmann::json());
}

// Refuses a detector directory whose data holds other frames than `frames`:
// "SUBJECT <verb> frames of X, not of Y: HINT".
void require_detector_frames(const fs::path& dir, const nlohmann::json& frames, const std::string& subject,
                             const std::string& hint) {
  const auto held = detector_frames_in(dir);
  DOJO_CHECK(held == frames,
             subject + " frames of " + held.dump() + ", not of " + frames.dump() + ": " + hint);
}

// Whether a training run in `dir` finished `steps` steps: its result.json is written at the end.
bool finished(const fs::path& dir, int64_t steps) {
  return fs::exists(dir / "result.json") &&
         read_json_file(dir / "result.json").value("steps", int64_t{-1}) == steps;
}

// One line on what the detector's result.json says of it: balanced accuracy on the held-out
// windows and on the held-out episodes by vote, in the frames it learnt from, and in DojoSim's
// when it learnt from a world model's.
std::string detector_summary(const nlohmann::json& result, bool world_model_frames) {
  const auto balanced = [](const nlohmann::json& part) {
    if (!part.is_object() || !part.contains("balanced_accuracy") || !part["balanced_accuracy"].is_number())
      return std::string("—");  // a result.json of another version: the report still gets written
    char buf[16];
    std::snprintf(buf, sizeof buf, "%.3f", part["balanced_accuracy"].get<double>());
    return std::string(buf);
  };
  const auto part = [](const nlohmann::json& j, const char* key) { return j.value(key, nlohmann::json()); };
  std::string line = "Success detector, balanced accuracy on held-out " +
                     std::string(world_model_frames ? "generated" : "DojoSim") + " frames: windows " +
                     balanced(part(result, "heldout")) + ", episodes by vote " +
                     balanced(part(result, "heldout_episodes"));
  if (result.contains("heldout_simulator_frames")) {
    const auto& simulated = result["heldout_simulator_frames"];
    line += "; the same episodes in DojoSim's frames: windows " + balanced(part(simulated, "heldout")) +
            ", episodes by vote " + balanced(part(simulated, "heldout_episodes"));
  }
  return line;
}

// The detector `policy eval` uses: --detector, or its own, trained into OUT on first use.
fs::path detector_directory(const PolicyEvalRun& a) {
  return pick(a.detector,
              fs::path(a.out) / (a.detector_frames == "world-model" ? "detector-world-model" : "detector"));
}

// The scene seeds a directory's data was made from (its data.json), else `fallback` (what training
// it here will use); nothing when neither is known.
std::optional<SeedRange> seeds_of(const std::string& what, const fs::path& dir,
                                  std::optional<SeedRange> fallback) {
  // A record whose data was never rendered (a crash mid-render) says what a rerun will replace.
  const auto record = training_data_record(dir);
  const auto run = record.empty() ? fs::path() : record.parent_path();
  const bool rendered =
      !record.empty() && (fs::exists(run / "demos.safetensors") || fs::exists(run / "readings.safetensors") ||
                          fs::exists(run / "data.safetensors") || checkpoint_exists(run / "checkpoint"));
  if (rendered) {
    const auto j = read_json_file(record);
    if (j.contains("seed") && j.contains("scenes"))
      return SeedRange{what, j["seed"].get<uint64_t>(), j["scenes"].get<int64_t>()};
    return std::nullopt;
  }
  if (fallback) fallback->what = what;
  return fallback;
}

// Whether the evaluated set holds the behaviour-cloning / reader family: by default, or when its run
// is named beside a policy-set file.
bool uses_bc(const PolicyEvalRun& a) { return !a.no_bc && (a.policies.empty() || !a.bc.empty()); }
bool uses_reader(const PolicyEvalRun& a) { return !a.no_reader && (a.policies.empty() || !a.reader.empty()); }

// Whether a scripted spec is one the detector learnt from (the same behaviour and quality).
bool seen_by_detector(const PolicySpec& spec, const std::vector<PolicySpec>& detector_set) {
  return spec.scripted() && std::any_of(detector_set.begin(), detector_set.end(), [&](const auto& d) {
           return d.scripted() && d.behavior == spec.behavior && d.quality == spec.quality;
         });
}

}  // namespace

nlohmann::json WorldModelSource::fingerprint() const {
  // Each model by path, size and time of its weights: one retrained in place is another model.
  nlohmann::json j = {{"world_model", checkpoint_fingerprint(checkpoint)},
                      {"tokenizer", checkpoint_fingerprint(tokenizer)},
                      {"fast_decoder", checkpoint_fingerprint(fast_decoder)},
                      {"device", device},
                      {"precision", precision}};
  if (teacher_steps > 0) j["teacher_steps"] = teacher_steps;  // absent: the trained sampler (older data)
  return j;
}

int64_t WorldModelSource::commands_per_step() const {
  return teacher ? infer::WorldModel::kChunkActions : infer::StreamingEngine::kActionsPerStep;
}

LoadedWorldModel::LoadedWorldModel() = default;
LoadedWorldModel::LoadedWorldModel(LoadedWorldModel&&) noexcept = default;
LoadedWorldModel& LoadedWorldModel::operator=(LoadedWorldModel&&) noexcept = default;
LoadedWorldModel::~LoadedWorldModel() = default;

LoadedWorldModel load_world_model(const WorldModelSource& s, models::SuccessDetector detector) {
  const auto device = parse_device(s.device);
  LoadedWorldModel loaded;
  loaded.per_step = s.commands_per_step();
  std::unique_ptr<infer::Generator> generator;
  nlohmann::json ranges;
  std::string name = "student";
  if (s.teacher) {
    loaded.teacher = std::make_unique<infer::WorldModel>(
        infer::WorldModel::load(s.checkpoint, s.tokenizer, device, parse_precision(s.precision)));
    ranges = loaded.teacher->action_ranges();
    generator = infer::make_teacher_generator(*loaded.teacher, nullptr, s.teacher_steps);
    name = "teacher";
  } else {
    infer::StreamingEngine::Options o;
    o.device = device;
    o.precision = parse_precision(s.precision);
    if (!s.fast_decoder.empty()) o.fast_decoder = models::load_fast_decoder(s.fast_decoder);
    auto engine = infer::StreamingEngine::load(s.checkpoint, s.tokenizer, o);
    ranges = engine.action_ranges();
    generator = infer::make_student_generator(std::move(engine));
  }
  DOJO_CHECK(ranges.size() == 1 && ranges.contains("dojosim_robot"),
             s.checkpoint.string() + ": the model's actions are " + ranges.dump() +
                 "; DojoSim's policies command the 'dojosim_robot' slot (6 values)");
  auto chunker = *data::single_slot_chunker(ranges, "model actions", static_cast<int>(loaded.per_step));
  loaded.environment = std::make_unique<eval::WorldModelEnvironment>(name, std::move(generator),
                                                                     std::move(chunker), std::move(detector));
  return loaded;
}

fs::path training_data_record(const fs::path& dir) {
  if (fs::exists(dir / "data.json")) return dir / "data.json";
  auto run = dir.lexically_normal();
  if (run.filename().empty()) run = run.parent_path();  // "RUN/checkpoint/"
  if (run.filename() != "checkpoint" || !fs::exists(run.parent_path() / "data.json")) return {};
  return run.parent_path() / "data.json";
}

void render_training_data_once(const fs::path& data, const nlohmann::json& made, const std::string& who,
                               const std::function<void()>& render) {
  const auto record = data.parent_path() / "data.json";
  if (fs::exists(data)) {
    if (!fs::exists(record)) return;  // an older run: nothing to compare
    const auto held = read_json_file(record);
    for (const auto& [key, value] : made.items())
      DOJO_CHECK(!held.contains(key) || held[key] == value,
                 who + ": " + data.string() + " was made with " + key + " " + held[key].dump() + ", not " +
                     value.dump() + ": give the settings its data.json records, or another --out");
    return;
  }
  write_file_atomic(record, made.dump(2) + "\n");
  render();
}

// Generates OUT/demos.safetensors once, then trains (or resumes) OUT/checkpoint with snapshots.
nlohmann::json train_bc(const BcRun& a) {
  const fs::path out = a.out;
  fs::create_directories(out);
  const auto demos = out / "demos.safetensors";
  // Under data parallelism rank 0 renders the demonstrations; the others then read them.
  train::data_parallel().main_first("the demonstrations", [&] {
    const nlohmann::json made = {
        {"seed", a.seed}, {"scenes", a.episodes}, {"frames", a.frames}, {"noise", a.noise}};
    render_training_data_once(demos, made, "policy train", [&] {
      DemonstrationOptions o;
      o.episodes = a.episodes;
      o.frames = a.frames;
      o.noise_std = a.noise;
      o.seed = a.seed;
      LOG_INFO("policy train: rendering ", a.episodes, " expert demonstrations in DojoSim");
      make_demonstrations(o, demos);
    });
  });
  train::BcTrainJob job;
  job.data = demos;
  job.out = out;
  job.steps = a.steps;
  job.batch_size = static_cast<int>(a.batch);
  job.accumulate = a.accumulate;
  job.snapshots = a.snapshots;
  job.shift = a.shift;
  job.device = a.device;
  job.precision = a.precision;
  const auto r = train::run_bc_training(job);
  nlohmann::json snapshots = nlohmann::json::array();
  for (const auto& s : r.snapshots) snapshots.push_back(s.string());
  const nlohmann::json result = {{"steps", r.steps},
                                 {"loss", r.loss},
                                 {"heldout_loss", r.heldout_loss},
                                 {"snapshots", snapshots},
                                 {"seconds", r.seconds}};
  write_file_atomic(out / "result.json", result.dump(2) + "\n");
  LOG_INFO("policy train: loss ", r.loss, ", held-out ", r.heldout_loss, "; ", r.snapshots.size(),
           " snapshots in ", (out / "snapshots").string());
  return result;
}

// Renders labelled frames once (OUT/readings.safetensors, OUT/data.json), then trains (or resumes)
// the scene reader with snapshots; OUT/result.json.
nlohmann::json train_reader(const ReaderRun& a) {
  const fs::path out = a.out;
  fs::create_directories(out);
  const auto readings = out / "readings.safetensors";
  train::data_parallel().main_first("the reader's frames", [&] {
    const nlohmann::json made = {{"seed", a.seed}, {"scenes", a.episodes}, {"frames", a.frames}};
    render_training_data_once(readings, made, "policy reader", [&] {
      ReaderDataOptions o;
      o.episodes = a.episodes;
      o.frames = a.frames;
      o.seed = a.seed;
      LOG_INFO("policy reader: rendering ", a.episodes, " labelled demonstrator episodes in DojoSim");
      make_reader_data(o, readings);
    });
  });
  train::ReaderTrainJob job;
  job.data = readings;
  job.out = out;
  job.steps = a.steps;
  job.batch_size = static_cast<int>(a.batch);
  job.accumulate = a.accumulate;
  job.snapshots = a.snapshots;
  const auto r = train::run_reader_training(job);
  nlohmann::json snapshots = nlohmann::json::array();
  for (const auto& snapshot : r.snapshots) snapshots.push_back(snapshot.string());
  const nlohmann::json result = {{"steps", r.steps},
                                 {"loss", r.loss},
                                 {"heldout",
                                  {{"frames", r.heldout.frames},
                                   {"object_cm", r.heldout.object_cm},
                                   {"bin_cm", r.heldout.bin_cm},
                                   {"grasp_height_cm", r.heldout.grasp_height_cm},
                                   {"in_bin_accuracy", r.heldout.in_bin_accuracy}}},
                                 {"snapshots", snapshots},
                                 {"seconds", r.seconds}};
  write_file_atomic(out / "result.json", result.dump(2) + "\n");
  LOG_INFO("policy reader: held-out frames: object ", r.heldout.object_cm, " cm, bin ", r.heldout.bin_cm,
           " cm, grasp height ", r.heldout.grasp_height_cm, " cm, in-bin calls ", r.heldout.in_bin_accuracy);
  return result;
}

// Generates DIR/data.safetensors once (DIR/data.json says from what), then trains (or resumes)
// DIR/checkpoint; DIR/result.json.
nlohmann::json train_detector(const DetectorRun& a) {
  const fs::path out = a.out;
  // The detector's shape first: a window longer than the episode fails before any rendering.
  models::SuccessDetectorConfig model;
  if (checkpoint_exists(out / "checkpoint")) {
    model = models::SuccessDetectorConfig::from_json(
        Checkpoint::open(resolve_checkpoint_dir(out / "checkpoint")).config().at("config"));
    DOJO_CHECK(
        a.window.value_or(model.window) == model.window && a.stride.value_or(model.stride) == model.stride,
        (out / "checkpoint").string() + " is a detector of window " + std::to_string(model.window) +
            ", stride " + std::to_string(model.stride) + ": resume it with those, or give another --out");
  } else {
    model.window = a.window.value_or(model.window);
    model.stride = a.stride.value_or(model.stride);
  }
  DOJO_CHECK(
      model.span() + models::kSuccessVotes - 1 <= 1 + a.frames + a.settle_frames,
      "policy detector: a window of " + std::to_string(model.window) + " frames " +
          std::to_string(model.stride) + " apart spans " + std::to_string(model.span()) + " frames; its " +
          std::to_string(models::kSuccessVotes) + " votes need episodes of at least " +
          std::to_string(model.span() + models::kSuccessVotes - 1) + " (1 + --frames + --settle-frames)");
  const auto& source = a.world_model;
  const nlohmann::json frames = source ? source->fingerprint() : nlohmann::json("dojosim");
  fs::create_directories(out);
  const auto data = out / "data.safetensors";
  std::optional<LoadedWorldModel> world_model;
  // Under data parallelism rank 0 renders the labelled episodes; the others then read them.
  const nlohmann::json made = {{"frames", frames},
                               {"scenes", a.scenes},
                               {"seed", a.seed},
                               {"frames_per_episode", a.frames},
                               {"settle_frames", a.settle_frames},
                               {"policies", a.policies.empty() ? "" : fs::absolute(a.policies).string()}};
  train::data_parallel().main_first("the detector's episodes", [&] {
    if (fs::exists(data))
      require_detector_frames(out, frames, data.string() + " holds", "give another --out");
    // The record goes first: data without it reads as DojoSim's.
    render_training_data_once(data, made, "policy detector", [&] {
      SuccessDataOptions o;
      o.scenes = a.scenes;
      o.seed = a.seed;
      std::optional<ScopedThreads> matmul_bound;  // the world model's replays, as in `policy eval`
      if (source) {
        if (a.replay_threads > 0) matmul_bound.emplace(a.replay_threads);
        world_model = load_world_model(*source, models::SuccessDetector{nullptr});
      }
      o.episode = episode_options(a.frames, a.settle_frames, world_model ? world_model->per_step : 4);
      LOG_INFO("policy detector: rendering ", a.scenes, " scenes per policy in DojoSim",
               world_model ? " and replaying them in the world model" : "");
      make_success_data(detector_training_set(a.policies), o, data,
                        world_model ? world_model->environment.get() : nullptr);
    });
  });
  world_model.reset();  // training needs the memory more
  train::SuccessTrainJob job;
  job.data = data;
  job.out = out;
  job.steps = a.steps;
  job.accumulate = a.accumulate;
  job.model = model;
  job.device = a.device;
  job.precision = a.precision;
  const auto r = train::run_success_training(job);
  const auto accuracy = [](const train::SuccessAccuracy& s) {
    return nlohmann::json{{"accuracy", s.accuracy},
                          {"balanced_accuracy", s.balanced_accuracy},
                          {"windows", s.windows},
                          {"success_windows", s.positives}};
  };
  const auto by_vote = [](const train::SuccessAccuracy& s) {
    return nlohmann::json{{"accuracy", s.accuracy},
                          {"balanced_accuracy", s.balanced_accuracy},
                          {"episodes", s.windows},
                          {"successes", s.positives}};
  };
  nlohmann::json result = {{"steps", r.steps},
                           {"loss", r.loss},
                           {"train", accuracy(r.train)},
                           {"heldout", accuracy(r.heldout)},
                           {"heldout_episodes", by_vote(r.heldout_episodes)},
                           {"window", model.window},
                           {"stride", model.stride},
                           {"seconds", r.seconds}};
  LOG_INFO("policy detector: held-out frames: accuracy ", r.heldout.accuracy, ", balanced ",
           r.heldout.balanced_accuracy, " (", r.heldout.windows,
           " windows); held-out episodes by vote: accuracy ", r.heldout_episodes.accuracy, ", balanced ",
           r.heldout_episodes.balanced_accuracy, " (", r.heldout_episodes.windows, " episodes)");
  if (r.simulator) {
    // Trained on a world model's replays: the same held-out episodes as DojoSim rendered them.
    result["heldout_simulator_frames"] = {{"heldout", accuracy(r.simulator->heldout)},
                                          {"heldout_episodes", by_vote(r.simulator->heldout_episodes)}};
    LOG_INFO("policy detector: the same held-out episodes in DojoSim's frames: balanced ",
             r.simulator->heldout.balanced_accuracy, " (windows), ",
             r.simulator->heldout_episodes.balanced_accuracy, " (episodes by vote)");
  }
  write_file_atomic(out / "result.json", result.dump(2) + "\n");
  return result;
}

// Refuses an evaluation whose scenes are among those the detector, the behaviour-cloning
// demonstrations or the reader's frames were made from, before anything is trained.
void check_scenes_held_out(const PolicyEvalRun& a) {
  std::vector<SeedRange> ranges = {{"the evaluation's scenes", a.seed, a.scenes}};
  const auto add = [&](std::optional<SeedRange> r) {
    if (r) ranges.push_back(*r);
  };
  if (!!a.world_model) {
    const DetectorRun d;
    add(seeds_of("the success detector's episodes", detector_directory(a),
                 a.detector.empty() ? std::optional(SeedRange{"", d.seed, d.scenes}) : std::nullopt));
  }
  if (uses_bc(a)) {
    const BcRun t;
    add(seeds_of("the behaviour-cloning demonstrations", pick(a.bc, fs::path(a.out) / "bc"),
                 a.bc.empty() ? std::optional(SeedRange{"", t.seed, t.episodes}) : std::nullopt));
  }
  if (uses_reader(a)) {
    const ReaderRun r;
    add(seeds_of("the scene reader's frames", pick(a.reader, fs::path(a.out) / "reader"),
                 a.reader.empty() ? std::optional(SeedRange{"", r.seed, r.episodes}) : std::nullopt));
  }
  check_disjoint_seeds(ranges);
}

PolicyEvalOutcome run_policy_eval(const PolicyEvalRun& a) {
  const fs::path out = a.out;
  check_scenes_held_out(a);
  fs::create_directories(out);

  std::optional<LoadedWorldModel> loaded;
  eval::Environment* world_model = nullptr;
  std::optional<DojoSimEnvironment> sim_as_world_model;
  std::string world_model_name = "DojoSim (as the world model)";
  nlohmann::json fingerprint;
  std::string detector_policies = a.detector_policies;  // what the detector learnt from
  int64_t per_step = infer::StreamingEngine::kActionsPerStep;
  if (!a.world_model) {
    world_model = &sim_as_world_model.emplace();
    fingerprint["world_model"] = "dojosim";
  } else {
    const auto& source = *a.world_model;
    const fs::path detector_dir = detector_directory(a);
    const nlohmann::json detector_frames =
        a.detector_frames == "world-model" ? source.fingerprint() : nlohmann::json("dojosim");
    if (a.detector.empty() && fs::exists(detector_dir / "data.safetensors"))
      require_detector_frames(detector_dir, detector_frames, detector_dir.string() + " was trained on",
                              "give another --out or --detector");
    if (a.detector.empty()
            ? !finished(detector_dir, a.detector_steps)
            : !checkpoint_exists(detector_dir / "checkpoint") && !checkpoint_exists(detector_dir)) {
      // Trained here, or resumed when an earlier run was interrupted.
      DOJO_CHECK(a.detector.empty(), "policy eval: no success detector at " + a.detector);
      DetectorRun d;
      d.out = detector_dir.string();
      d.policies = a.detector_policies;
      d.steps = a.detector_steps;
      d.frames = a.frames;
      d.settle_frames = a.settle_frames;
      if (a.detector_frames == "world-model") d.world_model = a.world_model;
      train_detector(d);
    }
    auto detector = models::load_success_detector(run_checkpoint(detector_dir));
    loaded = load_world_model(source, std::move(detector));
    world_model = loaded->environment.get();
    world_model_name = world_model->name();
    per_step = loaded->per_step;
    fingerprint = source.fingerprint();
    fingerprint["detector"] = checkpoint_fingerprint(detector_dir);
    // Seen or held out by what this detector learnt from: its own record, when it has one.
    if (const auto record = training_data_record(detector_dir); !record.empty()) {
      const auto made = read_json_file(record);
      const auto learnt = made.value("policies", a.detector_policies);
      if (learnt.empty() || fs::exists(learnt))
        detector_policies = learnt;
      else
        LOG_WARN("policy eval: the detector learnt from ", learnt, ", which is gone; seen and held out by ",
                 a.detector_policies.empty() ? "the demonstrators" : a.detector_policies);
    }
  }

  PolicySceneOptions scene_options;
  scene_options.count = a.scenes;
  scene_options.seed = a.seed;
  const auto scenes = make_policy_scenes(scene_options);
  // The evaluated set: the vision-only families (trained here when missing) unless --policies names
  // others (then a family joins when its directory is given); the demonstrators only when asked.
  std::vector<PolicySpec> specs =
      a.policies.empty() ? std::vector<PolicySpec>() : read_policy_set(a.policies);
  fs::path bc, reader;
  if (uses_bc(a)) bc = pick(a.bc, out / "bc");
  if (uses_reader(a)) reader = pick(a.reader, out / "reader");
  // A given run without snapshots fails before anything is trained.
  for (const auto& [given, family] : {std::pair{a.bc, "policy"}, std::pair{a.reader, "reader"}})
    DOJO_CHECK(given.empty() || !train::list_step_snapshots(given).empty(),
               given + ": no " + family + " snapshots");
  if (!bc.empty() && a.bc.empty() && !finished(bc, a.bc_steps)) {
    BcRun t;
    t.out = bc.string();
    t.steps = a.bc_steps;
    train_bc(t);
  }
  if (!reader.empty() && a.reader.empty() && !finished(reader, a.reader_steps)) {
    ReaderRun r;
    r.out = reader.string();
    r.steps = a.reader_steps;
    train_reader(r);
  }
  for (auto& s : vision_policy_set(bc, reader)) specs.push_back(std::move(s));
  if (a.with_scripted)
    for (auto& s : default_policy_set()) specs.push_back(std::move(s));
  for (const auto& e : a.external) specs.push_back(external_spec(e));
  std::vector<std::unique_ptr<eval::Policy>> owned;
  std::vector<eval::Policy*> policies;
  nlohmann::json names = nlohmann::json::array();
  const int64_t width = scenes.front().command.numel();
  // Held out: policies the detector never saw (every vision-only one); seen: the detector's own.
  const auto detector_set = detector_training_set(detector_policies);
  std::vector<std::string> held_out, seen;
  for (const auto& s : specs) {
    DOJO_CHECK(
        std::count_if(specs.begin(), specs.end(), [&](const auto& o) { return o.name == s.name; }) == 1,
        "policy eval: two policies are named '" + s.name + "'");
    owned.push_back(make_policy(s, width, a));
    policies.push_back(owned.back().get());
    nlohmann::json entry = {{"name", s.name}};
    if (!s.checkpoint.empty()) entry["checkpoint"] = checkpoint_fingerprint(s.checkpoint);
    if (!s.reader.empty()) entry["reader"] = checkpoint_fingerprint(s.reader);
    if (!s.command.empty()) entry["command"] = s.command;
    if (s.scripted()) entry["behavior"] = s.behavior;
    if (s.scripted() || !s.reader.empty()) entry["quality"] = s.quality;
    names.push_back(entry);
    (seen_by_detector(s, detector_set) ? seen : held_out).push_back(s.name);
  }
  auto options = episode_options(a.frames, a.settle_frames, per_step);
  options.videos = a.videos;
  options.video_dir = out / "videos";
  fingerprint["policies"] = names;
  fingerprint["scenes"] = {{"count", a.scenes}, {"seed", a.seed}};
  fingerprint["episode"] = {
      {"steps", options.steps}, {"settle_steps", options.settle_steps}, {"per_step", per_step}};

  DojoSimEnvironment real;
  std::optional<Progress> progress;  // over the episodes this run has left (a journal may hold others)
  const auto report =
      eval::evaluate_policies(policies, scenes, real, *world_model, options, out / "journal.jsonl",
                              fingerprint, [&](int64_t done, int64_t total) {
                                if (!progress) progress.emplace("policy eval", total - done + 1, "episode");
                                progress->advance();
                              });
  if (progress) progress->finish();
  auto json = report.to_json();
  // r, MMRV and Spearman over the held-out policies, and over the seen ones beside them.
  const auto group = [&](const std::vector<std::string>& names) {
    const auto rates = eval::rates_of(report.rates, names);
    nlohmann::json j = {{"policies", rates.names}};
    j["agreement"] = rates.names.size() >= 2 ? eval::policy_agreement(rates).to_json() : nlohmann::json();
    return j;
  };
  json["held_out"] = group(held_out);
  json["seen"] = group(seen);
  json["world_model"] = world_model_name;
  json["fingerprint"] = fingerprint;
  // The detector's run: the directory given, or the one above it when --detector named RUN/checkpoint.
  const auto detector_record = training_data_record(detector_directory(a));
  const auto detector_run = detector_record.empty() ? detector_directory(a) : detector_record.parent_path();
  std::string detector_line;
  if (!!a.world_model && fs::exists(detector_run / "result.json")) {
    json["detector"] = read_json_file(detector_run / "result.json");
    if (!detector_record.empty()) json["detector"]["data"] = read_json_file(detector_record);
    detector_line = detector_summary(json["detector"], detector_frames_in(detector_run) != "dojosim");
  }
  write_file_atomic(out / "report.json", json.dump(2) + "\n");
  eval::write_policy_eval_html(report, out / "report.html", "DojoSim", world_model_name, options.video_dir,
                               detector_line);

  PolicyEvalOutcome outcome;
  outcome.report = report;
  outcome.world_model_name = world_model_name;
  outcome.held_out = held_out;
  outcome.seen = seen;
  outcome.detector_line = detector_line;
  outcome.report_json = out / "report.json";
  outcome.report_html = out / "report.html";
  return outcome;
}

}  // namespace dojo::recipes
