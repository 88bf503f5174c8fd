// `dojo policy train | detector | eval`: policy evaluation in the world model against DojoSim
// (eval/policy_eval.h, recipes/dojosim_policies.h; docs/policy_eval.md).
#include <CLI/CLI.hpp>

#include <cmath>
#include <cstdio>
#include <iostream>
#include <optional>

#include "cli/commands.h"
#include "cli/model_args.h"
#include "cli/options.h"
#include "core/atomic_file.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "core/progress.h"
#include "core/runtime.h"
#include "eval/policy_eval.h"
#include "infer/generator.h"
#include "infer/streaming.h"
#include "infer/world_model.h"
#include "models/bc_policy.h"
#include "models/fast_decoder.h"
#include "recipes/dojosim_policies.h"
#include "serve/external_policy.h"
#include "train/bc_train.h"
#include "train/data_parallel.h"
#include "train/success_train.h"

namespace fs = std::filesystem;

namespace dojo::cli {
namespace {

// Which world model (policy eval and the detector's generated-video mode): the reference set's
// student unless told otherwise, else the demo's.
struct WorldModelArgs {
  std::string demo, student, teacher, tokenizer, fast_decoder;  // demo "": dojo_demo
  std::string device = "cpu", precision = "fp32";
  int teacher_steps = 0;  // the teacher's sampler steps (0: the ones it was trained with)
};

struct DetectorArgs {
  std::string out = "dojo_policy/detector", policies;
  int64_t scenes = 24, steps = 800, frames = 64, settle_frames = 12, accumulate = 1;
  // The detector's input, frames per decision and their spacing: for a new detector (defaults 3
  // and 1); a resumed one keeps its own, and refuses other values given here.
  std::optional<int64_t> window, stride;
  uint64_t seed = 9000;
  bool world_model = false;  // frames from the world model's replays, labels from DojoSim
  WorldModelArgs wm;
};

struct TrainArgs {
  std::string out = "dojo_policy/bc";
  int64_t episodes = 400, frames = 64, steps = 3000, batch = 64, shift = 0, accumulate = 1;
  std::vector<int64_t> snapshots = {200, 500, 1000};
  double noise = 0.03;
  uint64_t seed = 20000;
};

struct EvalArgs {
  std::string out = "dojo_policy", detector, policies, bc;
  WorldModelArgs wm;
  std::vector<std::string> external;
  int64_t scenes = 30, frames = 64, settle_frames = 12, detector_steps = 800, bc_steps = 3000, videos = 1;
  uint64_t seed = 7000;
  // What the detector trained here learns from. The world model's own replays by default: a
  // detector trained on DojoSim's frames reads generated video near chance (docs/policy_eval.md).
  std::string detector_frames = "world-model";
  bool sim_as_world_model = false, no_bc = false;
  double external_timeout = 120;
};

std::vector<recipes::PolicySpec> policy_set(const std::string& file) {
  return file.empty() ? recipes::default_policy_set() : recipes::read_policy_set(file);
}

// The policy a spec names. DojoSim's robot takes 6-value commands; a learned policy of another
// width is refused here, before any episode runs.
std::unique_ptr<eval::Policy> make_policy(const recipes::PolicySpec& spec, int64_t command_width,
                                          double external_timeout) {
  if (!spec.checkpoint.empty()) {
    auto model = models::load_bc_policy(spec.checkpoint);
    DOJO_CHECK(model->config().action_dim == command_width,
               "policy '" + spec.name + "' (" + spec.checkpoint.string() + "): its commands have " +
                   std::to_string(model->config().action_dim) + " values; the robot takes " +
                   std::to_string(command_width));
    return eval::make_bc_policy(spec.name, std::move(model));
  }
  if (!spec.command.empty()) {
    serve::ExternalPolicyOptions o;
    o.name = spec.name;
    o.command = spec.command;
    o.timeout_s = external_timeout;
    return serve::make_external_policy(o);
  }
  return recipes::make_scripted_policy(spec);
}

// Generates OUT/demos.safetensors once, then trains (or resumes) OUT/checkpoint with snapshots.
nlohmann::json train_bc(const TrainArgs& a) {
  const fs::path out = a.out;
  fs::create_directories(out);
  const auto demos = out / "demos.safetensors";
  // Under data parallelism rank 0 renders the demonstrations; the others then read them.
  train::data_parallel().main_first("the demonstrations", [&] {
    if (fs::exists(demos)) return;
    recipes::DemonstrationOptions o;
    o.episodes = a.episodes;
    o.frames = a.frames;
    o.noise_std = a.noise;
    o.seed = a.seed;
    LOG_INFO("policy train: rendering ", a.episodes, " expert demonstrations in DojoSim");
    recipes::make_demonstrations(o, demos);
  });
  train::BcTrainJob job;
  job.data = demos;
  job.out = out;
  job.steps = a.steps;
  job.batch_size = static_cast<int>(a.batch);
  job.accumulate = a.accumulate;
  job.snapshots = a.snapshots;
  job.shift = a.shift;
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

// Every snapshot of a behaviour-cloning run as a policy named bc-STEP.
std::vector<recipes::PolicySpec> bc_snapshot_specs(const fs::path& dir) {
  std::vector<recipes::PolicySpec> specs;
  for (const auto& snapshot : train::list_bc_snapshots(dir)) {
    recipes::PolicySpec s;
    s.name = "bc-" + std::to_string(std::stoll(snapshot.filename().string().substr(5)));
    s.checkpoint = snapshot;
    specs.push_back(s);
  }
  DOJO_CHECK(!specs.empty(),
             dir.string() + ": no policy snapshots (run `dojo policy train --out " + dir.string() + "`)");
  return specs;
}

// NAME=COMMAND
recipes::PolicySpec external_spec(const std::string& text) {
  const auto eq = text.find('=');
  DOJO_CHECK(eq != std::string::npos && eq > 0 && eq + 1 < text.size(),
             "--external: expected NAME=COMMAND, got '" + text + "'");
  recipes::PolicySpec s;
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

// The files a world model loads from, checked to exist, and how it runs.
struct WorldModelSource {
  fs::path checkpoint, tokenizer, fast_decoder;  // fast_decoder may be empty (the Wan decoder)
  bool teacher = false;
  int teacher_steps = 0;
  std::string device, precision;
  // What the model's frames depend on (journals and detector data record it).
  nlohmann::json fingerprint() const {
    const auto where = [](const fs::path& p) { return fs::absolute(p).lexically_normal().string(); };
    nlohmann::json j = {{"world_model", where(checkpoint)},
                        {"tokenizer", where(tokenizer)},
                        {"fast_decoder", fast_decoder.empty() ? "" : where(fast_decoder)},
                        {"device", device},
                        {"precision", precision}};
    if (teacher_steps > 0) j["teacher_steps"] = teacher_steps;  // absent: the trained sampler (older data)
    return j;
  }
};

// Without --demo, --student or --teacher: the reference set's student (with its tokenizer and fast
// decoder) where the set has one. Otherwise the demo's student unless `a` names others. `who`
// starts the error messages.
WorldModelSource resolve_world_model(const WorldModelArgs& a, const std::string& who) {
  WorldModelSource s;
  s.teacher = !a.teacher.empty();
  const auto reference = a.demo.empty() && a.student.empty() && !s.teacher ? reference_student() : fs::path();
  if (!reference.empty()) {
    s.checkpoint = reference;
    s.tokenizer = pick(a.tokenizer, default_reference_dir() / "tokenizer");
    s.fast_decoder = reference_model_fast_decoder(a.fast_decoder, !a.tokenizer.empty());
    LOG_INFO(who, ": the reference student ", s.checkpoint.string(),
             s.fast_decoder.empty() ? "" : ", decoded with " + s.fast_decoder.string());
  } else {
    const fs::path demo = a.demo.empty() ? "dojo_demo" : a.demo;
    s.checkpoint = s.teacher ? fs::path(a.teacher) : pick(a.student, demo / "student" / "checkpoint");
    s.tokenizer = pick(a.tokenizer, demo / "tokenizer" / "checkpoint");
    s.fast_decoder = a.fast_decoder;
    if (s.fast_decoder.empty() && a.student.empty() && !s.teacher &&
        fs::exists(demo / "fast_decoder" / "checkpoint"))
      s.fast_decoder = demo / "fast_decoder" / "checkpoint";
  }
  s.device = a.device;
  s.precision = a.precision;
  s.teacher_steps = a.teacher_steps;
  DOJO_CHECK(s.teacher_steps == 0 || s.teacher,
             who + ": --teacher-steps applies to a --teacher world model only (the student takes 4 hops)");
  DOJO_CHECK(checkpoint_exists(s.checkpoint),
             who + ": no world model at " + s.checkpoint.string() +
                 " (give --student or --teacher, or --demo DIR of a finished `dojo demo`)");
  DOJO_CHECK(checkpoint_exists(s.tokenizer), who + ": no tokenizer at " + s.tokenizer.string());
  DOJO_CHECK(s.fast_decoder.empty() || checkpoint_exists(s.fast_decoder),
             who + ": no fast decoder at " + s.fast_decoder.string());
  return s;
}

// A world model as an environment.
struct LoadedWorldModel {
  std::unique_ptr<infer::WorldModel> teacher;  // first: the environment refers to it
  std::unique_ptr<eval::WorldModelEnvironment> environment;
  int64_t per_step = infer::StreamingEngine::kActionsPerStep;  // commands per step
};

// Loads the student (or the teacher) of `s`; `detector` may be empty (frames only).
LoadedWorldModel load_world_model(const WorldModelSource& s, models::SuccessDetector detector) {
  const auto device = parse_device(s.device);
  LoadedWorldModel loaded;
  std::unique_ptr<infer::Generator> generator;
  nlohmann::json ranges;
  std::string name = "student";
  if (s.teacher) {
    loaded.teacher = std::make_unique<infer::WorldModel>(
        infer::WorldModel::load(s.checkpoint, s.tokenizer, device, parse_precision(s.precision)));
    ranges = loaded.teacher->action_ranges();
    generator = infer::make_teacher_generator(*loaded.teacher, nullptr, s.teacher_steps);
    loaded.per_step = infer::WorldModel::kChunkActions;
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

// The frames a detector directory's data holds: data.json's "frames"; an older directory without
// data.json holds DojoSim's.
nlohmann::json detector_frames_in(const fs::path& dir) {
  return fs::exists(dir / "data.json") ? read_json_file(dir / "data.json").value("frames", nlohmann::json())
                                       : nlohmann::json("dojosim");
}

// Refuses a detector directory whose data holds other frames than `frames`:
// "SUBJECT <verb> frames of X, not of Y: HINT".
void require_detector_frames(const fs::path& dir, const nlohmann::json& frames, const std::string& subject,
                             const std::string& hint) {
  const auto held = detector_frames_in(dir);
  DOJO_CHECK(held == frames,
             subject + " frames of " + held.dump() + ", not of " + frames.dump() + ": " + hint);
}

// Generates DIR/data.safetensors once (DIR/data.json says from what), then trains (or resumes)
// DIR/checkpoint; DIR/result.json.
nlohmann::json train_detector(const DetectorArgs& a) {
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
  std::optional<WorldModelSource> source;
  if (a.world_model) source = resolve_world_model(a.wm, "policy detector");
  const nlohmann::json frames = source ? source->fingerprint() : nlohmann::json("dojosim");
  fs::create_directories(out);
  const auto data = out / "data.safetensors";
  std::optional<LoadedWorldModel> world_model;
  // Under data parallelism rank 0 renders the labelled episodes; the others then read them.
  train::data_parallel().main_first("the detector's episodes", [&] {
    if (fs::exists(data)) {
      require_detector_frames(out, frames, data.string() + " holds", "give another --out");
    } else {
      recipes::SuccessDataOptions o;
      o.scenes = a.scenes;
      o.seed = a.seed;
      std::optional<ScopedThreads> matmul_bound;  // the world model's replays, as in `policy eval`
      if (source) {
        matmul_bound.emplace(
            matmul_bound_command_threads("policy detector", parse_device(source->device).is_cuda()));
        world_model = load_world_model(*source, models::SuccessDetector{nullptr});
      }
      o.episode = episode_options(a.frames, a.settle_frames, world_model ? world_model->per_step : 4);
      LOG_INFO("policy detector: rendering ", a.scenes, " scenes per policy in DojoSim",
               world_model ? " and replaying them in the world model" : "");
      auto specs = policy_set(a.policies);
      if (std::none_of(specs.begin(), specs.end(), [](const auto& s) { return s.scripted(); }))
        specs = recipes::default_policy_set();  // labelled episodes need scripted policies
      const nlohmann::json made = {{"frames", frames},
                                   {"scenes", a.scenes},
                                   {"seed", a.seed},
                                   {"frames_per_episode", a.frames},
                                   {"settle_frames", a.settle_frames},
                                   {"policies", a.policies}};
      write_file_atomic(out / "data.json", made.dump(2) + "\n");  // first: data without it reads as DojoSim's
      recipes::make_success_data(specs, o, data, world_model ? world_model->environment.get() : nullptr);
    }
  });
  world_model.reset();  // training needs the memory more
  train::SuccessTrainJob job;
  job.data = data;
  job.out = out;
  job.steps = a.steps;
  job.accumulate = a.accumulate;
  job.model = model;
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
fs::path detector_directory(const EvalArgs& a) {
  return pick(a.detector,
              fs::path(a.out) / (a.detector_frames == "world-model" ? "detector-world-model" : "detector"));
}

int run_eval(const EvalArgs& a) {
  const fs::path out = a.out;
  fs::create_directories(out);
  ScopedThreads matmul_bound(
      matmul_bound_command_threads("policy eval", parse_device(a.wm.device).is_cuda()));

  std::optional<LoadedWorldModel> loaded;
  eval::Environment* world_model = nullptr;
  std::optional<recipes::DojoSimEnvironment> sim_as_world_model;
  std::string world_model_name = "DojoSim (as the world model)";
  nlohmann::json fingerprint;
  int64_t per_step = infer::StreamingEngine::kActionsPerStep;
  if (a.sim_as_world_model) {
    world_model = &sim_as_world_model.emplace();
    fingerprint["world_model"] = "dojosim";
  } else {
    const auto source = resolve_world_model(a.wm, "policy eval");  // before any detector training
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
      DetectorArgs d;
      d.out = detector_dir.string();
      d.policies = a.policies;
      d.steps = a.detector_steps;
      d.frames = a.frames;
      d.settle_frames = a.settle_frames;
      d.world_model = a.detector_frames == "world-model";
      d.wm = a.wm;
      train_detector(d);
    }
    auto detector = models::load_success_detector(
        checkpoint_exists(detector_dir / "checkpoint") ? detector_dir / "checkpoint" : detector_dir);
    loaded = load_world_model(source, std::move(detector));
    world_model = loaded->environment.get();
    world_model_name = world_model->name();
    per_step = loaded->per_step;
    fingerprint = source.fingerprint();
    fingerprint["detector"] = fs::absolute(detector_dir).string();
  }

  recipes::PolicySceneOptions scene_options;
  scene_options.count = a.scenes;
  scene_options.seed = a.seed;
  const auto scenes = recipes::make_policy_scenes(scene_options);
  auto specs = policy_set(a.policies);
  if (!a.no_bc) {
    // The behaviour-cloning policy's snapshots, trained here when missing (or resumed).
    const fs::path bc = pick(a.bc, out / "bc");
    if (a.bc.empty() && !finished(bc, a.bc_steps)) {
      TrainArgs t;
      t.out = bc.string();
      t.steps = a.bc_steps;
      train_bc(t);
    }
    for (auto& s : bc_snapshot_specs(bc)) specs.push_back(std::move(s));
  }
  for (const auto& e : a.external) specs.push_back(external_spec(e));
  std::vector<std::unique_ptr<eval::Policy>> owned;
  std::vector<eval::Policy*> policies;
  nlohmann::json names = nlohmann::json::array();
  const int64_t width = scenes.front().command.numel();
  for (const auto& s : specs) {
    owned.push_back(make_policy(s, width, a.external_timeout));
    policies.push_back(owned.back().get());
    nlohmann::json entry = {{"name", s.name}};
    if (!s.checkpoint.empty()) entry["checkpoint"] = fs::absolute(s.checkpoint).string();
    if (!s.command.empty()) entry["command"] = s.command;
    if (s.scripted()) {
      entry["behavior"] = s.behavior;
      entry["quality"] = s.quality;
    }
    names.push_back(entry);
  }
  auto options = episode_options(a.frames, a.settle_frames, per_step);
  options.videos = a.videos;
  options.video_dir = out / "videos";
  fingerprint["policies"] = names;
  fingerprint["scenes"] = {{"count", a.scenes}, {"seed", a.seed}};
  fingerprint["episode"] = {
      {"steps", options.steps}, {"settle_steps", options.settle_steps}, {"per_step", per_step}};

  recipes::DojoSimEnvironment real;
  std::optional<Progress> progress;  // over the episodes this run has left (a journal may hold others)
  const auto report =
      eval::evaluate_policies(policies, scenes, real, *world_model, options, out / "journal.jsonl",
                              fingerprint, [&](int64_t done, int64_t total) {
                                if (!progress) progress.emplace("policy eval", total - done + 1, "episode");
                                progress->advance();
                              });
  if (progress) progress->finish();
  auto json = report.to_json();
  json["world_model"] = world_model_name;
  json["fingerprint"] = fingerprint;
  const auto detector_dir = detector_directory(a);
  std::string detector_line;
  if (!a.sim_as_world_model && fs::exists(detector_dir / "result.json")) {
    json["detector"] = read_json_file(detector_dir / "result.json");
    if (fs::exists(detector_dir / "data.json"))
      json["detector"]["data"] = read_json_file(detector_dir / "data.json");
    detector_line = detector_summary(json["detector"], detector_frames_in(detector_dir) != "dojosim");
  }
  write_file_atomic(out / "report.json", json.dump(2) + "\n");
  eval::write_policy_eval_html(report, out / "report.html", "DojoSim", world_model_name, options.video_dir,
                               detector_line);

  std::printf("%-14s %8s %12s\n", "policy", "DojoSim", world_model_name.substr(0, 12).c_str());
  for (size_t i = 0; i < report.rates.names.size(); ++i)
    std::printf("%-14s %8.3f %12.3f\n", report.rates.names[i].c_str(), report.rates.real[i],
                report.rates.world_model[i]);
  std::printf("pearson r %.4f  mmrv %.4f  spearman %.4f  mean |gap| %.4f\n", report.agreement.pearson,
              report.agreement.mmrv, report.agreement.spearman, report.agreement.mean_abs_gap);
  std::printf("episodes agreeing %.3f (open-loop replays %.3f); seconds per episode: DojoSim %.2f, %s %.2f\n",
              report.episode_agreement, report.open_loop_agreement, report.real_seconds_per_episode,
              world_model_name.c_str(), report.world_model_seconds_per_episode);
  if (!detector_line.empty()) std::printf("%s\n", detector_line.c_str());
  LOG_INFO("policy eval: ", (out / "report.json").string(), ", ", (out / "report.html").string());
  return 0;
}

void add_world_model_options(CLI::App* cmd, WorldModelArgs& wm) {
  cmd->add_option("--demo", wm.demo,
                  "Take the models from this `dojo demo` output (default: the reference set's student "
                  "when the set has one, else dojo_demo)");
  cmd->add_option("--student", wm.student,
                  "Student checkpoint (default: the reference set's, else the demo's)");
  cmd->add_option("--teacher", wm.teacher, "Use this teacher checkpoint instead (12-frame chunks)");
  cmd->add_option("--teacher-steps", wm.teacher_steps,
                  "With --teacher: sampler steps per chunk (default: the trained sampler's, 35)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--tokenizer", wm.tokenizer,
                  "Tokenizer checkpoint (default: the reference set's with its student, else the demo's)");
  cmd->add_option(
      "--fast-decoder", wm.fast_decoder,
      "Student's fast decoder (default: that of the reference set or demo the student comes from, "
      "when it has one)");
  add_device_option(cmd, wm.device);
  add_precision_option(cmd, wm.precision);
}

}  // namespace

void register_policy(CLI::App& app) {
  auto* policy =
      app.add_subcommand("policy", "Policy evaluation: rank policies in the world model against DojoSim");
  policy->require_subcommand(1);

  auto t = std::make_shared<TrainArgs>();
  auto* train_cmd = policy->add_subcommand(
      "train",
      "Render expert demonstrations in DojoSim and train the behaviour-cloning policy (frame + last "
      "command -> 4 commands); snapshots along training are policies of graded quality (resumable)");
  train_cmd->add_option("--out", t->out, "Output directory")->capture_default_str();
  train_cmd->add_option("--episodes", t->episodes, "Demonstration episodes")
      ->check(CLI::Range(2, 1000000))
      ->capture_default_str();
  train_cmd->add_option("--frames", t->frames, "Frames per demonstration")
      ->check(CLI::Range(8, 100000))
      ->capture_default_str();
  train_cmd->add_option("--noise", t->noise, "Noise injected into the executed arm commands (rad)")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  train_cmd
      ->add_option("--seed", t->seed, "First demonstration scene seed (keep apart from the evaluation's)")
      ->capture_default_str();
  train_cmd->add_option("--steps", t->steps, "Training steps")
      ->check(CLI::Range(0, 10000000))
      ->capture_default_str();
  train_cmd->add_option("--batch", t->batch, "Batch size")->check(CLI::Range(1, 4096))->capture_default_str();
  add_accumulate_option(train_cmd, t->accumulate);
  train_cmd->add_option("--shift", t->shift, "Random frame translation in pixels (augmentation)")
      ->check(CLI::Range(0, 16))
      ->capture_default_str();
  train_cmd
      ->add_option("--snapshots", t->snapshots, "Steps whose weights are kept as policies (besides the last)")
      ->delimiter(',')
      ->capture_default_str();
  train_cmd->callback([t] { set_action([t] { return train_bc(*t).is_object() ? 0 : 1; }); });

  auto d = std::make_shared<DetectorArgs>();
  auto* detector = policy->add_subcommand(
      "detector", "Render labelled DojoSim episodes and train the success detector on them (resumable)");
  detector->add_option("--out", d->out, "Output directory")->capture_default_str();
  detector->add_option("--policies", d->policies, "Policy set JSON (default: the built-in 13)");
  detector->add_option("--scenes", d->scenes, "Scenes per policy")
      ->check(CLI::Range(2, 100000))
      ->capture_default_str();
  detector->add_option("--seed", d->seed, "First scene seed (use others than the evaluation's)")
      ->capture_default_str();
  detector->add_option("--steps", d->steps, "Training steps")
      ->check(CLI::Range(0, 10000000))
      ->capture_default_str();
  add_accumulate_option(detector, d->accumulate);
  detector->add_option("--frames", d->frames, "Frames each policy acts for (as `policy eval --frames`)")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  detector
      ->add_option("--settle-frames", d->settle_frames, "Frames holding the last command (as `policy eval`)")
      ->check(CLI::Range(0, 100000))
      ->capture_default_str();
  detector
      ->add_option("--window", d->window,
                   "Frames one decision sees (default 3; a resumed detector keeps its own)")
      ->check(CLI::Range(1, 64));
  detector
      ->add_option("--stride", d->stride,
                   "Frames between a window's frames (default 1; > 1: the window spans more of the episode)")
      ->check(CLI::Range(1, 64));
  detector->add_flag("--world-model", d->world_model,
                     "Train on the world model's replays of the episodes (labels from DojoSim): the "
                     "detector then reads generated video as `policy eval` shows it");
  add_world_model_options(detector, d->wm);
  detector->callback([d] { set_action([d] { return train_detector(*d).is_object() ? 0 : 1; }); });

  auto e = std::make_shared<EvalArgs>();
  auto* ev =
      policy->add_subcommand("eval",
                             "Run every policy closed loop in DojoSim and in the world model; Pearson r, "
                             "MMRV, Spearman, success gap; JSON + HTML (resumable)");
  ev->add_option("--out", e->out, "Output directory")->capture_default_str();
  add_world_model_options(ev, e->wm);
  ev->add_option(
      "--detector", e->detector,
      "Success detector (default: OUT/detector-world-model or OUT/detector, trained when missing)");
  ev->add_option("--detector-steps", e->detector_steps, "Training steps when the detector is trained here")
      ->capture_default_str();
  ev->add_option("--detector-frames", e->detector_frames,
                 "What a detector trained here learns from: DojoSim's frames, or the world model's "
                 "replays of the same episodes (labels from DojoSim either way)")
      ->check(CLI::IsMember({"dojosim", "world-model"}))
      ->capture_default_str();
  ev->add_option("--policies", e->policies, "Policy set JSON (default: the built-in 13 scripted policies)");
  ev->add_option("--bc", e->bc,
                 "Add the snapshots of this `dojo policy train` run (default: OUT/bc, trained when missing)");
  ev->add_flag("--no-bc", e->no_bc, "Leave the behaviour-cloning policies out");
  ev->add_option("--bc-steps", e->bc_steps,
                 "Training steps when the behaviour-cloning policy is trained here")
      ->capture_default_str();
  ev->add_option(
      "--external", e->external,
      "NAME=COMMAND: a policy in another process speaking the step protocol (docs/policy_eval.md); "
      "repeatable");
  ev->add_option("--external-timeout", e->external_timeout, "Seconds an external policy may take to answer")
      ->check(CLI::Range(1.0, 1e6))
      ->capture_default_str();
  ev->add_option("--scenes", e->scenes, "Scenes per policy")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  ev->add_option("--seed", e->seed, "First scene seed")->capture_default_str();
  ev->add_option("--frames", e->frames, "Frames each policy acts for")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  ev->add_option("--settle-frames", e->settle_frames,
                 "Frames holding the last command before success is read")
      ->check(CLI::Range(0, 100000))
      ->capture_default_str();
  ev->add_option("--videos", e->videos,
                 "Scenes per policy written as side-by-side videos (OUT/videos, in the report)")
      ->check(CLI::Range(0, 100000))
      ->capture_default_str();
  ev->add_flag("--sim-as-world-model", e->sim_as_world_model,
               "Plug DojoSim in as the world model too (checks the harness: r = 1, MMRV = 0)");
  ev->callback([e] { set_action([e] { return run_eval(*e); }); });
}

}  // namespace dojo::cli
