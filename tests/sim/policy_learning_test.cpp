// The policies of policy evaluation that are not scripted: the behaviour-cloning policy learns
// from DojoSim demonstrations and its snapshots act; an external process speaking the step
// protocol runs closed loop in both worlds; `dojo policy train | eval` end to end with their
// one-line errors.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>

#include "core/checkpoint.h"
#include "eval/policy_eval.h"
#include "recipes/dojosim_policies.h"
#include "recipes/policy_eval.h"
#include "serve/external_policy.h"
#include "sim/policy_scenes.h"
#include "test_util.h"
#include "train/bc_train.h"
#include "train/success_train.h"

namespace dojo::recipes {
namespace {

namespace fs = std::filesystem;

TEST(BcPolicy, LearnsFromDemonstrationsAndItsSnapshotsAct) {
  test::OneThread one;
  test::TempDir tmp;
  DemonstrationOptions o;
  o.episodes = 10;
  o.frames = 40;
  o.heldout_fraction = 0.2;
  make_demonstrations(o, tmp / "demos.safetensors");
  const auto data = train::Demonstrations::load(tmp / "demos.safetensors");
  ASSERT_EQ(data.frames.sizes(), (std::vector<int64_t>{10, 40, 64, 64, 3}));
  EXPECT_EQ(data.heldout.sum().item<int64_t>(), 2);
  // The executed commands carry the injected noise, the labels do not.
  EXPECT_GT((data.executed.narrow(1, 1, 39) - data.labels.narrow(1, 0, 39)).abs().max().item<double>(), 1e-3);
  // The expert moves: its labels leave the start command.
  EXPECT_GT((data.labels - data.executed.narrow(1, 0, 1)).abs().max().item<double>(), 0.2);

  train::BcTrainJob job;
  job.data = tmp / "demos.safetensors";
  job.out = tmp / "bc";
  job.steps = 150;
  job.save_every = 0;
  job.snapshots = {0, 50};
  job.batch_size = 32;
  const auto r = train::run_bc_training(job);
  ASSERT_EQ(r.snapshots.size(), 3u);  // steps 0, 50 and the last
  EXPECT_EQ(r.snapshots.back().filename(), "step-000150");
  auto untrained = models::load_bc_policy(r.snapshots.front());
  auto trained = models::load_bc_policy(r.snapshots.back());
  // It fits its demonstrations (ten episodes are too few to expect much on held-out ones, where
  // the error still has to fall).
  const auto seen = data.heldout.logical_not();
  const double fit_before = train::bc_loss(untrained, data, seen),
               fit_after = train::bc_loss(trained, data, seen);
  EXPECT_LT(fit_after, 0.7 * fit_before) << "training offset error " << fit_after << " vs " << fit_before;
  const double before = train::bc_loss(untrained, data, data.heldout);
  EXPECT_LT(r.heldout_loss, before) << "held-out offset error " << r.heldout_loss << " vs " << before;

  // As a policy: 4 commands a decision, 12 for a teacher-sized step, finite, from the last command.
  const auto policy = eval::make_bc_policy("bc", trained);
  const auto start = test::policy_scenes(1)[0];
  policy->reset(start);
  const auto chunk = policy->act(start.frame.unsqueeze(0), start.command, 4);
  EXPECT_EQ(chunk.sizes(), (std::vector<int64_t>{4, 6}));
  EXPECT_TRUE(torch::isfinite(chunk).all().item<bool>());
  EXPECT_EQ(policy->act(start.frame.unsqueeze(0), start.command, 12).size(0), 12);
  EXPECT_LT((chunk[0] - start.command).abs().max().item<double>(), 1.0)
      << "a chunk starts near the last command";
}

fs::path example(const std::string& name) { return fs::path(DOJO_SOURCE_DIR) / "examples" / name; }

// Records the commands of every episode it runs.
class RecordingEnvironment : public DojoSimEnvironment {
 public:
  torch::Tensor reset(const eval::EpisodeStart& start) override {
    episodes.emplace_back();
    return DojoSimEnvironment::reset(start);
  }
  torch::Tensor step(const torch::Tensor& commands) override {
    episodes.back().push_back(commands.clone());
    return DojoSimEnvironment::step(commands);
  }
  std::vector<std::vector<torch::Tensor>> episodes;
};

TEST(PolicyEval, ExternalProcessSpeaksTheStepProtocolInBothWorlds) {
  test::OneThread one;
  test::TempDir tmp;
  const auto starts = test::policy_scenes(2);
  std::vector<std::unique_ptr<eval::Policy>> owned;
  for (const auto& spec : default_policy_set())
    if (spec.name == "expert" || spec.name == "idle") owned.push_back(make_scripted_policy(spec));
  serve::ExternalPolicyOptions o;
  o.name = "python-wiggle";
  o.command = "python3 " + example("policy_client.py").string() + " --behavior wiggle --summary " +
              (tmp / "summary.json").string();
  o.timeout_s = 60;
  owned.push_back(serve::make_external_policy(o));
  std::vector<eval::Policy*> policies;
  for (const auto& p : owned) policies.push_back(p.get());
  RecordingEnvironment real, twin;
  const eval::PolicyEvalOptions options;  // 16 steps of 4 commands, then 3 settle steps
  const auto report = eval::evaluate_policies(policies, starts, real, twin, options);
  ASSERT_EQ(report.rates.names.back(), "python-wiggle");
  EXPECT_EQ(report.agreement.pearson, 1.0);
  // What the process decided is what both worlds ran: the client sways the base joint by
  // 0.05 sin(t / 3) from the last command it sent, starting at the start command it was told.
  for (auto* env : {&real, &twin}) {
    ASSERT_EQ(env->episodes.size(), 3u * 2u);
    for (size_t scene = 0; scene < 2; ++scene) {
      const auto& steps = env->episodes[4 + scene];  // expert (2), idle (2), then the process
      ASSERT_EQ(steps.size(), 16u + 3u);
      auto command = starts[scene].command.to(torch::kFloat64);
      for (int64_t k = 0; k < 16; ++k) {
        auto expected = command.unsqueeze(0).repeat({4, 1});
        for (int64_t i = 0; i < 4; ++i)
          expected[i][0] = command[0].item<double>() + 0.05 * std::sin(static_cast<double>(4 * k + i) / 3);
        EXPECT_TRUE(torch::allclose(steps[k].to(torch::kFloat64), expected, 0, 1e-5)) << "step " << k;
        command = expected[3];
      }
    }
  }
  owned.clear();  // the process wrote its summary when its connection closed
  const auto summary = nlohmann::json::parse(test::read_file(tmp / "summary.json"));
  EXPECT_EQ(summary.at("episodes"), 4);               // 2 scenes x 2 worlds
  EXPECT_EQ(summary.at("steps"), 4 * 16);             // every decision went through the process
  EXPECT_EQ(summary.at("frames"), 4 * (1 + 15 * 4));  // start frame + the frames of steps 1..15
}

TEST(PolicyEval, ExternalProcessErrorsAreOneLineAndBadMessagesAreAnswered) {
  test::OneThread one;
  test::TempDir tmp;
  serve::ExternalPolicyOptions o;
  o.name = "quits";
  o.command = "exit 3";
  o.timeout_s = 20;
  // The process starts with the policy's first episode.
  auto message =
      test::error_message([&] { serve::make_external_policy(o)->reset(test::policy_scenes(1)[0]); });
  EXPECT_NE(message.find("external policy 'quits': the process exited (status 3) before connecting"),
            std::string::npos)
      << message;

  // A client that sends junk, a step before start, a wrong-width step, then behaves; it records
  // the errors it was sent.
  const auto script = tmp / "client.py";
  std::ofstream(script) << "import json, os, sys\n"
                        << "sys.path.insert(0, " << nlohmann::json(example("").string()).dump() << ")\n"
                        << R"(from step_client import WorldModelSession, TEXT, WorldModelError
s = WorldModelSession(os.environ["DOJO_POLICY_URL"])
errors = []
def expect_error(payload):
    s.ws.send(TEXT, payload.encode())
    try:
        s._next()
    except WorldModelError as e:
        errors.append(str(e))
expect_error("not json")
expect_error(json.dumps({"type": "step", "actions": [[0] * 6] * 4}))
ready = s.start()
expect_error(json.dumps({"type": "step", "actions": [[0] * 5] * 4}))
expect_error(json.dumps({"type": "step", "actions": [["x"] * 6] * 4}))
try:
    while True:
        s.step([ready["command"]] * ready["actions_per_step"])
        if s.last_step_done.get("done"):
            break
except WorldModelError:
    pass
json.dump(errors, open(sys.argv[1], "w"))
)";
  o.name = "clumsy";
  o.command = "python3 " + script.string() + " " + (tmp / "errors.json").string();
  {
    auto policy = serve::make_external_policy(o);
    DojoSimEnvironment env;
    eval::PolicyEvalOptions options;
    options.steps = 3;
    const auto start = test::policy_scenes(1)[0];
    EXPECT_EQ(eval::run_policy_episode(*policy, env, start, options), 0.0);
  }
  const auto errors = nlohmann::json::parse(test::read_file(tmp / "errors.json"));
  ASSERT_EQ(errors.size(), 4u) << errors.dump();
  EXPECT_NE(errors[0].get<std::string>().find("expected a JSON object"), std::string::npos);
  EXPECT_NE(errors[1].get<std::string>().find("send {\"type\":\"start\"} first"), std::string::npos);
  EXPECT_NE(errors[2].get<std::string>().find("expected 4 raw commands of 6 values, got [4, 5]"),
            std::string::npos);
  EXPECT_NE(errors[3].get<std::string>().find("values must be finite numbers"), std::string::npos);
}

TEST(PolicyCli, TrainThenEvaluateWithTheSimulatorAsTheWorldModel) {
  test::TempDir tmp;
  const auto bc = tmp / "bc";
  auto r = test::run_dojo("--threads 1 policy train --out " + bc.string() +
                          " --episodes 4 --frames 24 --steps 6 --batch 8 --snapshots 0,3");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(fs::exists(bc / "snapshots" / "step-000003" / "config.json"));
  EXPECT_TRUE(fs::exists(bc / "result.json"));

  std::ofstream(tmp / "set.json")
      << R"({"policies": [{"name": "expert"}, {"name": "idle", "behavior": "idle"},
      {"name": "late-bc", "checkpoint": "bc/snapshots/step-000006"}]})";
  const auto out = tmp / "eval";
  r = test::run_dojo(
      "--threads 1 policy eval --sim-as-world-model --scenes 2 "
      "--policies " +
      (tmp / "set.json").string() + " --bc " + bc.string() + " --out " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto report = nlohmann::json::parse(test::read_file(out / "report.json"));
  ASSERT_EQ(report.at("policies").size(), 6u);  // 3 from the file + bc-0, bc-3, bc-6
  EXPECT_EQ(report.at("policies")[3].at("name"), "bc-0");
  EXPECT_EQ(report.at("agreement").at("pearson_r"), 1.0);
  EXPECT_EQ(report.at("agreement").at("mmrv"), 0.0);
  // One filmed scene per policy (the default), both worlds side by side, in the report too.
  EXPECT_TRUE(fs::exists(out / "videos" / "bc-3-scene-0.mp4"));
  EXPECT_FALSE(fs::exists(out / "videos" / "bc-3-scene-1.mp4"));
  const auto html = test::read_file(out / "report.html");
  EXPECT_NE(html.find("<video"), std::string::npos);
  EXPECT_NE(html.find("bc-3, scene 0: "), std::string::npos);

  // One-line errors: a bad policy file, a policy of another action space, a missing snapshot dir.
  const auto one_line = [](const test::CommandResult& res, const std::string& expected) {
    EXPECT_NE(res.exit_code, 0);
    EXPECT_NE(res.output.find(expected), std::string::npos) << res.output;
  };
  std::ofstream(tmp / "bad.json") << R"({"policies": [{"name": "x", "checkpoint": "nowhere"}]})";
  one_line(test::run_dojo("policy eval --sim-as-world-model --no-bc --policies " +
                          (tmp / "bad.json").string() + " --out " + (tmp / "e2").string()),
           "bad.json: policies[0]: no checkpoint at");
  std::ofstream(tmp / "both.json")
      << R"({"policies": [{"name": "x", "command": "true", "behavior": "idle"}]})";
  one_line(test::run_dojo("policy eval --sim-as-world-model --no-bc --policies " +
                          (tmp / "both.json").string() + " --out " + (tmp / "e3").string()),
           "give one of");
  one_line(test::run_dojo("policy eval --sim-as-world-model --bc " + (tmp / "none").string() + " --out " +
                          (tmp / "e4").string()),
           "no policy snapshots");
  models::BcPolicyConfig seven;
  seven.action_dim = 7;
  save_checkpoint(tmp / "seven", models::bc_policy_checkpoint(*models::BcPolicy(seven)));
  std::ofstream(tmp / "seven.json") << R"({"policies": [{"name": "x", "checkpoint": "seven"}]})";
  one_line(test::run_dojo("policy eval --sim-as-world-model --no-bc --policies " +
                          (tmp / "seven.json").string() + " --out " + (tmp / "e5").string()),
           "policy 'x' (" + (tmp / "seven").string() + "): its commands have 7 values; the robot takes 6");
}

// `policy reader` trains the scene reader; its snapshots and the knob variants join an evaluation
// as reader policies, reported apart from the scripted ones the detector learnt from; scenes shared
// with the reader's frames or the detector's episodes are refused before anything runs.
TEST(PolicyCli, ReaderPoliciesAreHeldOutAndSharedScenesAreRefused) {
  test::TempDir tmp;
  const auto reader = tmp / "reader";
  auto r = test::run_dojo("--threads 1 policy reader --out " + reader.string() +
                          " --episodes 4 --frames 16 --steps 6 --batch 8 --snapshots 0,3");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(fs::exists(reader / "snapshots" / "step-000006" / "config.json"));
  const auto made = nlohmann::json::parse(test::read_file(reader / "data.json"));
  EXPECT_EQ(made.at("seed"), 30000);
  EXPECT_EQ(made.at("scenes"), 4);
  EXPECT_TRUE(
      nlohmann::json::parse(test::read_file(reader / "result.json")).at("heldout").contains("object_cm"));
  // The same directory with other data settings is refused, not trained on the old frames.
  r = test::run_dojo("policy reader --out " + reader.string() + " --episodes 5 --frames 16 --steps 6");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("readings.safetensors was made with scenes 4, not 5: give the settings its "
                          "data.json records, or another --out"),
            std::string::npos)
      << r.output;

  std::ofstream(tmp / "set.json")
      << R"({"policies": [{"name": "expert"}, {"name": "idle", "behavior": "idle"}]})";
  const auto out = tmp / "eval";
  r = test::run_dojo("--threads 1 policy eval --sim-as-world-model --scenes 1 --videos 0 --policies " +
                     (tmp / "set.json").string() + " --reader " + reader.string() + " --out " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto report = nlohmann::json::parse(test::read_file(out / "report.json"));
  ASSERT_EQ(report.at("policies").size(), 2u + 3u + 6u);
  EXPECT_EQ(report.at("policies")[2].at("name"), "reader-0");
  EXPECT_EQ(report.at("seen").at("policies"), (nlohmann::json{"expert", "idle"}));
  EXPECT_EQ(report.at("held_out").at("policies").size(), 9u);
  EXPECT_EQ(report.at("held_out").at("policies")[0], "reader-0");

  r = test::run_dojo("policy eval --sim-as-world-model --no-bc --reader " + reader.string() +
                     " --seed 30002 --scenes 2 --out " + (tmp / "e2").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("the evaluation's scenes (seeds 30002-30003) and the scene reader's frames (seeds "
                          "30000-30003) share scenes"),
            std::string::npos)
      << r.output;
  r = test::run_dojo("policy eval --seed 9010 --scenes 4 --out " + (tmp / "e3").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("and the success detector's episodes (seeds 9000-9023) share scenes"),
            std::string::npos)
      << r.output;
  EXPECT_FALSE(fs::exists(tmp / "e3"));
}

// A run's data.json is found from the run or from its checkpoint (what --detector and --value take).
TEST(PolicyCli, TrainingDataRecordLiesInTheRunOrBesideItsCheckpoint) {
  test::TempDir tmp;
  fs::create_directories(tmp / "run" / "checkpoint");
  EXPECT_EQ(recipes::training_data_record(tmp / "run"), fs::path());
  std::ofstream(tmp / "run" / "data.json") << R"({"seed": 1, "scenes": 2})";
  EXPECT_EQ(recipes::training_data_record(tmp / "run"), tmp / "run" / "data.json");
  EXPECT_EQ(recipes::training_data_record(tmp / "run" / "checkpoint"), tmp / "run" / "data.json");
  EXPECT_EQ(recipes::training_data_record(tmp / "run" / "checkpoint/"), tmp / "run" / "data.json");
  fs::create_directories(tmp / "run" / "other");
  EXPECT_EQ(recipes::training_data_record(tmp / "run" / "other"), fs::path());
}

// The Gymnasium-style environment (examples/gym_env.py) with a LeRobot-style policy on it
// (examples/gym_policy.py) is evaluated as an external policy in both worlds, held out.
TEST(PolicyCli, AGymnasiumStylePolicyIsEvaluatedInBothWorlds) {
  test::TempDir tmp;
  std::ofstream(tmp / "set.json") << R"({"policies": [{"name": "idle", "behavior": "idle"}]})";
  const auto summary = tmp / "summary.json";
  const auto r = test::run_dojo(
      "--threads 1 policy eval --sim-as-world-model --scenes 1 --frames 8 --settle-frames 4 --videos 0 "
      "--policies " +
      (tmp / "set.json").string() + " --external \"sway=python3 " + example("gym_policy.py").string() +
      " --summary " + summary.string() + "\" --out " + (tmp / "eval").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto report = nlohmann::json::parse(test::read_file(tmp / "eval" / "report.json"));
  EXPECT_EQ(report.at("held_out").at("policies"), (nlohmann::json{"sway"}));
  EXPECT_EQ(report.at("seen").at("policies"), (nlohmann::json{"idle"}));
  const auto counts = nlohmann::json::parse(test::read_file(summary));
  EXPECT_EQ(counts.at("episodes"), 2);          // 1 scene x 2 worlds
  EXPECT_EQ(counts.at("steps"), 2 * 2);         // 8 frames: 2 decisions of 4 commands
  EXPECT_EQ(counts.at("frames"), 2 * (1 + 4));  // the start frame + the first step's frames
}

TEST(PolicyCli, DetectorLearnsFromWorldModelReplaysAndTheEvaluationUsesIt) {
  test::TempDir tmp;
  const fs::path reference = fs::path(DOJO_SOURCE_DIR) / "models" / "reference";
  const std::string model = " --student " + (reference / "wm_posttrain").string() + " --tokenizer " +
                            (reference / "tokenizer").string();
  std::ofstream(tmp / "set.json")
      << R"({"policies": [{"name": "expert"}, {"name": "idle", "behavior": "idle"}]})";
  const std::string set = " --policies " + (tmp / "set.json").string();
  const std::string short_episodes = set + " --frames 8 --settle-frames 4";
  const auto detector = tmp / "detector";
  // Whole episodes (64 + 12 frames): the expert's success comes late.
  auto r = test::run_dojo("--threads 1 policy detector --world-model --scenes 2 --steps 10" + model + set +
                          " --out " + detector.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto made = nlohmann::json::parse(test::read_file(detector / "data.json"));
  EXPECT_EQ(made.at("frames").at("world_model").at("path"),
            fs::absolute(reference / "wm_posttrain").string());
  const auto data = train::SuccessData::load(detector / "data.safetensors");
  EXPECT_EQ(data.frames.size(1), 1 + 64 + 12);
  EXPECT_GT(data.labels.sum().item<double>(), 0);  // the expert's endings: both classes to learn
  EXPECT_EQ(data.simulator_frames.sizes(), data.frames.sizes());
  const auto result = nlohmann::json::parse(test::read_file(detector / "result.json"));
  EXPECT_TRUE(result.at("heldout_simulator_frames").contains("heldout_episodes")) << result.dump();

  const auto out = tmp / "eval";
  r = test::run_dojo("--threads 1 policy eval --no-bc --scenes 1 --videos 0 --detector " + detector.string() +
                     model + short_episodes + " --out " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto report = nlohmann::json::parse(test::read_file(out / "report.json"));
  EXPECT_EQ(report.at("policies").size(), 2u);
  EXPECT_EQ(report.at("detector").at("data").at("frames"), made.at("frames"));
  EXPECT_NE(r.output.find("Success detector, balanced accuracy on held-out generated frames: windows "),
            std::string::npos)
      << r.output;
  EXPECT_NE(r.output.find("; the same episodes in DojoSim's frames: windows "), std::string::npos)
      << r.output;

  // One-line errors: frames of another source in the same directory (to train on or to reuse in
  // an evaluation), no world model.
  r = test::run_dojo("policy eval --no-bc --detector-frames world-model --student " +
                     (reference / "wm_posttrain").string() + " --demo " + (tmp / "nodemo").string() +
                     " --out " + out.string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("policy eval: no tokenizer at"), std::string::npos) << r.output;
  r = test::run_dojo("policy detector --scenes 2 --steps 10" + short_episodes + " --out " +
                     detector.string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("data.safetensors holds frames of"), std::string::npos) << r.output;
  r = test::run_dojo("policy detector --world-model --student " + (tmp / "nowhere").string() + " --out " +
                     (tmp / "d2").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("no world model at " + (tmp / "nowhere").string()), std::string::npos) << r.output;
  // The detector's window: a resumed detector keeps its own (3 consecutive frames here) and
  // refuses another; a window longer than the episodes is refused before anything is rendered.
  r = test::run_dojo("policy detector --world-model --scenes 2 --steps 20 --window 4" + model + set +
                     " --out " + detector.string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("is a detector of window 3, stride 1: resume it with those"), std::string::npos)
      << r.output;
  r = test::run_dojo("policy detector --window 4 --stride 8" + short_episodes + " --out " +
                     (tmp / "d3").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("spans 25 frames; its 5 votes need episodes of at least 29"), std::string::npos)
      << r.output;
  EXPECT_FALSE(fs::exists(tmp / "d3" / "data.safetensors"));
}

}  // namespace
}  // namespace dojo::recipes
