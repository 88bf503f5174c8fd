// Policy evaluation in a world model (the paper's headline use): every policy runs closed loop in
// the real world and in the world model from the same start frames; success rates per policy in
// the two are compared by Pearson r, MMRV, Spearman rho and the mean absolute gap (eval/metrics.h).
// DojoSim stands in for the real world here (its state says who succeeded); in the world model,
// where there is no state, a success detector reads the outcome off the generated frames.
//
// One episode (run_policy_episode):
//   frames = [env.reset(start)]                       frame 0, [1, H, W, 3] uint8
//   repeat `steps` times:  commands = policy.act(frames, last command, n)    [n, w] raw units
//                          frames = env.step(commands)                       the n new frames
//   repeat `settle_steps` times: env.step(the last command, n times)        the scene comes to rest
//   success = env.success()
// n is the world model's actions per step (4 for the student), so a policy decides on each new
// latent frame. Policies see frames and their own commands only, never simulator state, so the
// same policy runs in both worlds.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "data/actions.h"
#include "eval/metrics.h"
#include "models/bc_policy.h"
#include "models/success_detector.h"

namespace dojo::infer {
class Generator;
}

namespace dojo::eval {

// What every world and every policy of one scene agree on.
struct EpisodeStart {
  int64_t index = 0;      // the scene's place in the evaluation
  uint64_t seed = 0;      // the scene's seed (world-model noise and policy randomness derive from it)
  nlohmann::json scene;   // the world's own description of the scene (DojoSim: its SceneSpec)
  torch::Tensor frame;    // frame 0, [H, W, 3] uint8
  torch::Tensor command;  // the command in force at frame 0, [w] float (raw units)
};

class Policy {
 public:
  virtual ~Policy() = default;
  virtual const std::string& name() const = 0;
  // True when the policy plans its commands at reset and ignores the frames: its world-model
  // episodes are open-loop replays whose real outcome is known (the detector's check).
  virtual bool open_loop() const { return false; }
  virtual void reset(const EpisodeStart& start) = 0;
  // frames [k, H, W, 3] uint8, those shown since the last decision (the newest last; at the
  // first decision the start frame), last_command [w] -> the next `n` commands [n, w].
  virtual torch::Tensor act(const torch::Tensor& frames, const torch::Tensor& last_command, int64_t n) = 0;
  // No episode follows (the evaluation is done with this policy): release what it holds.
  virtual void finish() {}
};

class Environment {
 public:
  virtual ~Environment() = default;
  virtual std::string name() const = 0;
  // Starts the scene; returns frame 0 as this world shows it, [H, W, 3] uint8.
  virtual torch::Tensor reset(const EpisodeStart& start) = 0;
  // Raw commands [n, w] -> the n frames they lead to, [n, H, W, 3] uint8.
  virtual torch::Tensor step(const torch::Tensor& commands) = 0;
  // The episode's success in [0, 1], after its last step.
  virtual double success() = 0;
  // Commands a step takes at once (0: any number).
  virtual int64_t actions_per_step() const { return 0; }
};

// A world model as an environment: raw commands become the model's action rows through its own
// normalisation (data::ActionChunker, baseline = the start command), frames come from the
// generator, and success is the detector's vote over the last frames (1 when more than half of
// the last `votes` windows see success). Without a detector (an empty holder) it only makes
// frames: success() throws.
class WorldModelEnvironment : public Environment {
 public:
  WorldModelEnvironment(std::string name, std::unique_ptr<infer::Generator> generator,
                        data::ActionChunker chunker, models::SuccessDetector detector,
                        int64_t votes = models::kSuccessVotes);
  ~WorldModelEnvironment() override;
  std::string name() const override { return name_; }
  torch::Tensor reset(const EpisodeStart& start) override;
  torch::Tensor step(const torch::Tensor& commands) override;
  double success() override;
  int64_t actions_per_step() const override;
  // The episode's frames so far, [T, H, W, 3] uint8.
  torch::Tensor video() const;

 private:
  std::string name_;
  std::unique_ptr<infer::Generator> generator_;
  data::ActionChunker chunker_;
  models::SuccessDetector detector_;
  int64_t votes_;
  std::vector<torch::Tensor> frames_;  // [n, H, W, 3] pieces
};

struct PolicyEvalOptions {
  int64_t steps = 16;        // policy decisions per episode (x n actions: 64 frames for the student)
  int64_t settle_steps = 3;  // steps holding the last command before success is read
  int64_t actions_per_step = 4;
  // Scenes 0 .. videos-1 of every policy are written as side-by-side videos (the real world | the
  // world model, enlarged 4x, each labelled with its outcome) into video_dir/POLICY-scene-K.mp4.
  int64_t videos = 0;
  std::filesystem::path video_dir;
};

struct EpisodeResult {
  std::string policy;
  int64_t scene = 0;
  double real = 0, world_model = 0;  // success in [0, 1]
  double real_seconds = 0, world_model_seconds = 0;
  bool open_loop = false;
  nlohmann::json to_json() const;
  static EpisodeResult from_json(const nlohmann::json& j);
};

struct PolicyEvalReport {
  std::vector<EpisodeResult> episodes;
  PolicyRates rates;  // per policy, mean success over the scenes
  PolicyAgreement agreement;
  // Episodes where the world model's binary outcome (> 0.5) equals the real one: over all, and
  // over open-loop policies (replays with a known outcome: the detector's accuracy on generated video).
  double episode_agreement = 0, open_loop_agreement = 0;
  double real_seconds_per_episode = 0, world_model_seconds_per_episode = 0;
  nlohmann::json to_json() const;
};

// The behaviour-cloning policy (models/bc_policy.h) as a policy: it decides on the newest frame
// and executes the first commands of its chunk. A step longer than its chunk is filled by
// deciding again on the same frame from the chunk's end, open loop.
std::unique_ptr<Policy> make_bc_policy(std::string name, models::BcPolicy policy);

// One episode of `policy` in `env` from `start` (see the top of this file). Throws dojo::Error
// naming the policy when it returns commands of the wrong shape or non-finite values.
// With `frames`, every frame the episode showed is appended to it ([k, H, W, 3] pieces, the start
// frame first).
double run_policy_episode(Policy& policy, Environment& env, const EpisodeStart& start,
                          const PolicyEvalOptions& options, std::vector<torch::Tensor>* frames = nullptr);

// Every policy on every scene in both worlds. With `journal`, finished episodes are appended to
// it (one JSON line each, flushed) and a rerun with the same journal skips them: a crashed
// evaluation resumes. The journal's first line holds `fingerprint` (what was evaluated: models,
// scenes, options); a journal of another evaluation is refused. on_episode(done, total) after
// each episode pair.
PolicyEvalReport evaluate_policies(const std::vector<Policy*>& policies,
                                   const std::vector<EpisodeStart>& scenes, Environment& real,
                                   Environment& world_model, const PolicyEvalOptions& options,
                                   const std::filesystem::path& journal = {},
                                   const nlohmann::json& fingerprint = nlohmann::json::object(),
                                   const std::function<void(int64_t, int64_t)>& on_episode = {});

// The rates of the policies named in `names` only, in the order of `rates`.
PolicyRates rates_of(const PolicyRates& rates, const std::vector<std::string>& names);

// Aggregates episode results (policies in first-seen order).
PolicyEvalReport summarize_policy_episodes(const std::vector<EpisodeResult>& episodes);

// The report as a self-contained HTML page: the agreement numbers, a scatter of per-policy
// success (real vs world model), the per-policy table, `detector_note` (what the success detector
// reads, when given) and the episode videos in `video_dir`.
void write_policy_eval_html(const PolicyEvalReport& report, const std::filesystem::path& path,
                            const std::string& real_name, const std::string& world_model_name,
                            const std::filesystem::path& video_dir = {},
                            const std::string& detector_note = {});

}  // namespace dojo::eval
