// The policy-evaluation pipeline behind `dojo policy train | reader | detector | eval`: the
// vision-only policies trained from DojoSim's demonstrators, the success detector, and the
// evaluation of every policy in DojoSim and in a world model (eval/policy_eval.h says what an
// episode is; recipes/vision_policies.h what the policies see; docs/policy_eval.md).
//
// Held out by construction: the evaluated set is vision-only (behaviour cloning and reader
// policies) while the detector learns from the scripted demonstrators; the evaluation's scenes are
// refused when they share a seed with the detector's episodes, the demonstrations or the reader's
// frames. Every stage is resumable: a rerun continues a training run and skips finished episodes.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/autocast.h"
#include "eval/policy_eval.h"
#include "models/success_detector.h"
#include "recipes/dojosim_policies.h"

namespace dojo::infer {
class WorldModel;
}

namespace dojo::recipes {

// The files a world model loads from (checked to exist by whoever resolves them) and how it runs.
struct WorldModelSource {
  std::filesystem::path checkpoint, tokenizer, fast_decoder;  // fast_decoder may be empty (the Wan decoder)
  bool teacher = false;
  int teacher_steps = 0;  // the teacher's sampler steps (0: the ones it was trained with)
  std::string device = "cpu", precision = "fp32";
  // What the model's frames depend on (journals and detector data record it).
  nlohmann::json fingerprint() const;
  // Commands one step of the loaded model takes: the student's 4, the teacher's chunk of 12.
  int64_t commands_per_step() const;
};

// A world model as an environment (eval/policy_eval.h): the student, or the teacher with its
// sampler, behind the model's own action chunker.
struct LoadedWorldModel {
  std::unique_ptr<infer::WorldModel> teacher;  // first: the environment refers to it
  std::unique_ptr<eval::WorldModelEnvironment> environment;
  int64_t per_step = 4;  // commands per step (the student's 4, the teacher's 12)
  LoadedWorldModel();
  LoadedWorldModel(LoadedWorldModel&&) noexcept;
  LoadedWorldModel& operator=(LoadedWorldModel&&) noexcept;
  ~LoadedWorldModel();
};
// Loads the student (or the teacher) of `source`; `detector` may be empty (frames only). Throws
// dojo::Error when the model's actions are not DojoSim's robot slot.
LoadedWorldModel load_world_model(const WorldModelSource& source, models::SuccessDetector detector);

// The data.json of the training run at DIR: DIR/data.json, or the run's own when DIR is its
// checkpoint (RUN/checkpoint); empty when there is none.
std::filesystem::path training_data_record(const std::filesystem::path& dir);

// Training data rendered once: DATA's directory's data.json records `made` (the seeds, scenes and
// settings it is made from) before `render` writes DATA, so an interrupted render still leaves the
// seeds to check held-out sets against. When DATA exists and data.json records another value for a
// key of `made`, refuses (dojo::Error naming the key, both values and `who`): a rerun with other
// settings would otherwise train on the old data. Keys data.json lacks (older runs) are not checked.
void render_training_data_once(const std::filesystem::path& data, const nlohmann::json& made,
                               const std::string& who, const std::function<void()>& render);

// The behaviour-cloning run (OUT/demos.safetensors rendered once, OUT/checkpoint, OUT/snapshots).
struct BcRun {
  std::string out = "dojo_policy/bc";
  int64_t episodes = 400, frames = 64, steps = 3000, batch = 64, shift = 0, accumulate = 1;
  std::vector<int64_t> snapshots = {200, 500, 1000};
  double noise = 0.03;
  uint64_t seed = 20000;
  torch::Device device = torch::kCPU;  // where the policy trains (rendering stays in DojoSim)
  Precision precision = Precision::kFloat32;
};
nlohmann::json train_bc(const BcRun& run);  // OUT/result.json's content

// The scene reader's run (OUT/readings.safetensors rendered once, OUT/checkpoint, OUT/snapshots).
struct ReaderRun {
  std::string out = "dojo_policy/reader";
  int64_t episodes = 160, frames = 64, steps = 2000, batch = 64, accumulate = 1;
  std::vector<int64_t> snapshots = {0, 100, 300, 800};
  uint64_t seed = 30000;
};
nlohmann::json train_reader(const ReaderRun& run);

// The success detector's run (OUT/data.safetensors rendered once, OUT/data.json says from what).
struct DetectorRun {
  std::string out = "dojo_policy/detector";
  std::string policies;  // a policy-set file whose scripted policies it learns from ("": the 13)
  int64_t scenes = 24, steps = 800, frames = 64, settle_frames = 12, accumulate = 1;
  // The detector's input, frames per decision and their spacing: for a new detector (defaults 3
  // and 1); a resumed one keeps its own, and refuses other values given here.
  std::optional<int64_t> window, stride;
  uint64_t seed = 9000;
  // Frames from this world model's replays of the episodes (labels from DojoSim); none: DojoSim's.
  std::optional<WorldModelSource> world_model;
  int replay_threads = 0;              // intra-op threads while the world model replays (0: as they are)
  torch::Device device = torch::kCPU;  // where the detector trains
  Precision precision = Precision::kFloat32;
};
nlohmann::json train_detector(const DetectorRun& run);

struct PolicyEvalRun {
  std::string out = "dojo_policy";
  std::optional<WorldModelSource> world_model;  // none: DojoSim plays the world model too (the harness check)
  std::string detector;  // "": OUT/detector-world-model (or OUT/detector), trained here
  std::string detector_frames = "world-model";  // what a detector trained here learns from: or "dojosim"
  std::string detector_policies;                // its policy-set file ("": the 13 scripted demonstrators)
  int64_t detector_steps = 800;
  std::string policies;    // a policy-set file evaluated instead of the vision-only set
  std::string bc, reader;  // "": OUT/bc, OUT/reader, trained here when missing
  int64_t bc_steps = 3000, reader_steps = 2000;
  bool no_bc = false, no_reader = false;
  bool with_scripted = false;         // also the scripted demonstrators (seen by the detector)
  std::vector<std::string> external;  // NAME=COMMAND
  // Starts an external policy (a spec with a command): the server layer's, given by the caller.
  std::function<std::unique_ptr<eval::Policy>(const PolicySpec&)> make_external;
  int64_t scenes = 30, frames = 64, settle_frames = 12, videos = 1;
  uint64_t seed = 7000;
};

struct PolicyEvalOutcome {
  eval::PolicyEvalReport report;
  std::string world_model_name;
  std::vector<std::string> held_out, seen;  // policies the detector never saw / learnt from
  std::string detector_line;                // what the detector's result says of it ("" without one)
  std::filesystem::path report_json, report_html;
};

// Refuses (dojo::Error naming both) evaluation scenes that share a seed with the detector's
// episodes, the demonstrations or the reader's frames; before anything is trained.
void check_scenes_held_out(const PolicyEvalRun& run);

// Trains what is missing, evaluates (resuming OUT/journal.jsonl), writes OUT/report.json and
// OUT/report.html.
PolicyEvalOutcome run_policy_eval(const PolicyEvalRun& run);

}  // namespace dojo::recipes
