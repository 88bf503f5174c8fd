// Policy evaluation (eval/policy_eval.h) with DojoSim's scenes and scripted policies
// (recipes/dojosim_policies.h): the plumbing is exact when the simulator stands in for the world
// model, journals resume, bad policies are named, the success detector learns, and a world model
// runs a policy closed loop and replays the detector's training episodes.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <fstream>

#include "core/error.h"
#include "eval/policy_eval.h"
#include "infer/generator.h"
#include "infer/streaming.h"
#include "recipes/dojosim_policies.h"
#include "sim/policy_scenes.h"
#include "test_util.h"
#include "train/success_train.h"

namespace dojo::recipes {
namespace {

namespace fs = std::filesystem;

std::vector<std::unique_ptr<eval::Policy>> policies(const std::vector<std::string>& names) {
  std::vector<std::unique_ptr<eval::Policy>> out;
  for (const auto& spec : default_policy_set())
    if (std::find(names.begin(), names.end(), spec.name) != names.end())
      out.push_back(make_scripted_policy(spec));
  return out;
}

std::vector<eval::Policy*> pointers(const std::vector<std::unique_ptr<eval::Policy>>& owned) {
  std::vector<eval::Policy*> out;
  for (const auto& p : owned) out.push_back(p.get());
  return out;
}

// Counts the episodes it is asked to start.
class CountingEnvironment : public DojoSimEnvironment {
 public:
  torch::Tensor reset(const eval::EpisodeStart& start) override {
    ++resets;
    return DojoSimEnvironment::reset(start);
  }
  int resets = 0;
};

TEST(PolicyEval, SimulatorAsTheWorldModelAgreesExactlyAndJournalsResume) {
  test::OneThread one;
  test::TempDir tmp;
  const auto starts = test::policy_scenes(3);
  ASSERT_EQ(starts.size(), 3u);
  EXPECT_EQ(starts[0].frame.sizes(), (std::vector<int64_t>{64, 64, 3}));
  EXPECT_EQ(starts[0].command.numel(), 6);
  const auto owned = policies({"expert", "poor", "idle"});
  ASSERT_EQ(owned.size(), 3u);
  DojoSimEnvironment real;
  CountingEnvironment twin;
  const eval::PolicyEvalOptions options;  // 16 steps of 4 commands, 3 settle steps
  const nlohmann::json fingerprint = {{"test", 1}};
  const auto report = eval::evaluate_policies(pointers(owned), starts, real, twin, options,
                                              tmp / "journal.jsonl", fingerprint);
  EXPECT_EQ(twin.resets, 9);
  ASSERT_EQ(report.rates.names, (std::vector<std::string>{"expert", "poor", "idle"}));
  EXPECT_EQ(report.rates.real, report.rates.world_model);
  EXPECT_EQ(report.agreement.pearson, 1.0);
  EXPECT_EQ(report.agreement.mmrv, 0.0);
  EXPECT_EQ(report.agreement.mean_abs_gap, 0.0);
  EXPECT_EQ(report.episode_agreement, 1.0);
  // The expert puts the object in the bin; holding still never does.
  EXPECT_GE(report.rates.real[0], 2.0 / 3);
  EXPECT_EQ(report.rates.real[2], 0.0);

  // A rerun with the same journal runs nothing and reports the same.
  CountingEnvironment again;
  const auto resumed = eval::evaluate_policies(pointers(owned), starts, real, again, options,
                                               tmp / "journal.jsonl", fingerprint);
  EXPECT_EQ(again.resets, 0);
  EXPECT_EQ(resumed.rates.real, report.rates.real);
  // A journal of another evaluation is refused.
  const auto message = test::error_message([&] {
    eval::evaluate_policies(pointers(owned), starts, real, again, options, tmp / "journal.jsonl",
                            {{"test", 2}});
  });
  EXPECT_NE(message.find("written by another policy evaluation"), std::string::npos) << message;
  // A crash while writing the last record leaves it torn: that episode is run again, once, and
  // the journal reads whole afterwards.
  auto text = test::read_file(tmp / "journal.jsonl");
  text.resize(text.rfind('\n', text.size() - 2) + 1);  // drop the last record ...
  std::ofstream(tmp / "journal.jsonl", std::ios::trunc)
      << text << R"({"policy": "idle", "sce)";  // ... half written
  CountingEnvironment rerun;
  const auto mended = eval::evaluate_policies(pointers(owned), starts, real, rerun, options,
                                              tmp / "journal.jsonl", fingerprint);
  EXPECT_EQ(rerun.resets, 1);
  EXPECT_EQ(mended.rates.real, report.rates.real);
  CountingEnvironment none;
  eval::evaluate_policies(pointers(owned), starts, real, none, options, tmp / "journal.jsonl", fingerprint);
  EXPECT_EQ(none.resets, 0);
}

// Returns commands of the wrong width.
class WidePolicy : public eval::Policy {
 public:
  const std::string& name() const override { return name_; }
  void reset(const eval::EpisodeStart&) override {}
  torch::Tensor act(const torch::Tensor&, const torch::Tensor&, int64_t n) override {
    return torch::zeros({n, 7});
  }

 private:
  std::string name_ = "wide";
};

TEST(PolicyEval, BadPoliciesAndPolicyFilesGetOneLineErrors) {
  test::TempDir tmp;
  const auto starts = test::policy_scenes(1);
  DojoSimEnvironment env;
  WidePolicy wide;
  auto message = test::error_message([&] { eval::run_policy_episode(wide, env, starts[0], {}); });
  EXPECT_NE(message.find("policy 'wide': expected 4 commands of width 6"), std::string::npos) << message;

  const auto bad = [&](const std::string& text, const std::string& expected) {
    const auto file = tmp / "policies.json";
    std::ofstream(file) << text;
    const auto m = test::error_message([&] { read_policy_set(file); });
    EXPECT_NE(m.find(expected), std::string::npos) << m;
    EXPECT_NE(m.find(file.string()), std::string::npos) << m;
    EXPECT_EQ(m.find('\n'), std::string::npos) << m;
  };
  bad("[1, 2]", "expected {\"policies\"");
  bad(R"({"policies": [{"behavior": "bin_pick"}]})", "policies[0]: needs a non-empty string 'name'");
  bad(R"({"policies": [{"name": "a"}, {"name": "a"}]})", "policies[1]: the name 'a' is used twice");
  bad(R"({"policies": [{"name": "a", "behavior": "dance"}]})", "unknown robot behavior 'dance'");
  bad(R"({"policies": [{"name": "a", "quality": {"noise": 1}}]})", "unknown knob 'noise'");
  bad(R"({"policies": [{"name": "a", "quality": "superb"}]})", "unknown policy quality 'superb'");
  bad(R"({"policies": [{"name": "a", "quality": {"miss_prob": 2}}]})", "probabilities must be in [0, 1]");
  std::ofstream(tmp / "good.json")
      << R"({"policies": [{"name": "a"}, {"name": "b", "quality": {"speed": 0.8}}]})";
  EXPECT_EQ(read_policy_set(tmp / "good.json").size(), 2u);
  EXPECT_GE(default_policy_set().size(), 10u);
  for (const auto& spec : default_policy_set())  // every default policy builds from its knobs
    EXPECT_NE(make_scripted_policy(spec), nullptr) << spec.name;
}

TEST(PolicyEval, SuccessDetectorLearnsFromLabelledFrames) {
  test::OneThread one;
  test::TempDir tmp;
  SuccessDataOptions o;
  o.scenes = 10;
  o.heldout_fraction = 0.3;
  std::vector<PolicySpec> specs;
  for (const auto& s : default_policy_set())
    if (s.name == "expert" || s.name == "idle") specs.push_back(s);
  make_success_data(specs, o, tmp / "data.safetensors");
  const auto data = train::SuccessData::load(tmp / "data.safetensors");
  EXPECT_EQ(data.frames.size(0), 20);
  EXPECT_EQ(data.frames.size(1), 1 + 4 * (16 + 3));
  EXPECT_GT(data.labels.sum().item<double>(), 0);    // some expert frames show success
  EXPECT_EQ(data.heldout.sum().item<int64_t>(), 6);  // 3 of 10 scenes for each policy

  train::SuccessTrainJob job;
  job.data = tmp / "data.safetensors";
  job.out = tmp / "detector";
  job.steps = 300;
  job.save_every = 0;
  const auto r = train::run_success_training(job);
  const auto curve = test::read_file(tmp / "detector" / "loss.csv");
  EXPECT_LT(r.loss, 0.35);  // from ln 2 = 0.69 at chance
  EXPECT_GT(r.train.balanced_accuracy, 0.85);
  EXPECT_GT(r.heldout.balanced_accuracy, 0.75);
  // The saved detector's vote over each held-out episode's ending (an expert's success, an idle
  // or failed ending): the episode-level score is exactly that vote, and it reads most of them.
  auto detector = models::load_success_detector(tmp / "detector" / "checkpoint");
  const auto T = data.frames.size(1);
  int positives = 0, negatives = 0, true_positives = 0, true_negatives = 0;
  for (int64_t e = 0; e < data.frames.size(0); ++e) {
    if (!data.heldout[e].item<bool>()) continue;
    const bool success = data.labels[e][T - 1].item<double>() > 0.5;
    const bool voted = models::success_vote(detector, data.frames[e]) > 0.5;
    (success ? positives : negatives) += 1;
    if (voted == success) (success ? true_positives : true_negatives) += 1;
  }
  EXPECT_EQ(r.heldout_episodes.windows, 6);
  EXPECT_EQ(r.heldout_episodes.positives, positives);
  ASSERT_GT(positives, 0);  // both outcomes among them, so the score means something
  ASSERT_GT(negatives, 0);
  const double by_hand = 0.5 * (static_cast<double>(true_positives) / positives +
                                static_cast<double>(true_negatives) / negatives);
  EXPECT_DOUBLE_EQ(r.heldout_episodes.balanced_accuracy, by_hand);
  // At most one of the 6 episodes misread (the exact count depends on the BLAS's rounding).
  EXPECT_GE(true_positives + true_negatives, 5);
  EXPECT_FALSE(r.simulator.has_value());  // DojoSim's frames only

  // Data with the simulator's frames beside the shown ones, and other frames than those: the
  // episodes in reverse order, so an expert's label meets an idle episode's frames and the other
  // way round. The finished detector, resumed at its last step, is trained on the shown frames
  // and scored on the simulator's, under the same labels: its score there is the one read off
  // those frames by hand, and far from its score on the shown frames.
  auto both = data;
  both.simulator_frames = data.frames.flip(0).contiguous();
  ASSERT_FALSE(torch::equal(both.simulator_frames, both.frames));
  both.save(tmp / "both.safetensors");
  job.data = tmp / "both.safetensors";
  const auto scored = train::run_success_training(job);
  EXPECT_EQ(scored.steps, r.steps);  // resumed, not trained further
  EXPECT_DOUBLE_EQ(scored.heldout.balanced_accuracy, r.heldout.balanced_accuracy);
  ASSERT_TRUE(scored.simulator.has_value());
  const train::SuccessData simulated{both.simulator_frames, data.labels, data.heldout, {}};
  const auto windows_by_hand = train::success_accuracy(detector, simulated, data.heldout);
  int sim_true_positives = 0, sim_true_negatives = 0;
  for (int64_t e = 0; e < data.frames.size(0); ++e) {
    if (!data.heldout[e].item<bool>()) continue;
    const bool success = data.labels[e][T - 1].item<double>() > 0.5;
    const bool voted = models::success_vote(detector, both.simulator_frames[e]) > 0.5;
    if (voted == success) (success ? sim_true_positives : sim_true_negatives) += 1;
  }
  const double sim_by_hand = 0.5 * (static_cast<double>(sim_true_positives) / positives +
                                    static_cast<double>(sim_true_negatives) / negatives);
  // The two kinds of frames score apart, so the check below tells which ones were read.
  ASSERT_LT(windows_by_hand.balanced_accuracy, r.heldout.balanced_accuracy - 0.25);
  ASSERT_LT(sim_by_hand, r.heldout_episodes.balanced_accuracy - 0.25);
  EXPECT_DOUBLE_EQ(scored.simulator->heldout.balanced_accuracy, windows_by_hand.balanced_accuracy);
  EXPECT_DOUBLE_EQ(scored.simulator->heldout.accuracy, windows_by_hand.accuracy);
  EXPECT_EQ(scored.simulator->heldout.windows, r.heldout.windows);
  EXPECT_EQ(scored.simulator->heldout.positives, r.heldout.positives);  // the same labels
  EXPECT_DOUBLE_EQ(scored.simulator->heldout_episodes.balanced_accuracy, sim_by_hand);
  EXPECT_EQ(scored.simulator->heldout_episodes.windows, 6);
  both.simulator_frames = data.frames.narrow(1, 0, 5).clone();
  both.save(tmp / "short.safetensors");
  EXPECT_NE(test::error_message([&] {
              train::SuccessData::load(tmp / "short.safetensors");
            }).find("short.safetensors: 'simulator_frames' must be uint8 of the shape of 'frames'"),
            std::string::npos);
}

TEST(PolicyEval, DetectorWindowSpansItsStride) {
  models::SuccessDetectorConfig c;
  c.window = 3;
  c.stride = 4;
  EXPECT_EQ(c.span(), 9);
  const auto video = torch::arange(20, torch::kUInt8).view({20, 1, 1, 1}).expand({20, 8, 8, 3}).contiguous();
  const auto w = models::window_ending_at(c, video, 19);  // frames 11, 15, 19
  ASSERT_EQ(w.size(0), 3);
  EXPECT_EQ(w[0][0][0][0].item<int>(), 11);
  EXPECT_EQ(w[1][0][0][0].item<int>(), 15);
  EXPECT_EQ(w[2][0][0][0].item<int>(), 19);
  EXPECT_THROW(models::window_ending_at(c, video, 7), Error);   // would start before frame 0
  EXPECT_THROW(models::window_ending_at(c, video, 20), Error);  // past the last frame
  // Saved with its stride; a config written before strides existed reads as stride 1.
  EXPECT_EQ(models::SuccessDetectorConfig::from_json(c.to_json()).stride, 4);
  EXPECT_EQ(models::SuccessDetectorConfig::from_json({{"window", 3}, {"size", 64}, {"width", 24}}).stride, 1);
  try {
    models::SuccessDetectorConfig::from_json({{"window", 3}, {"stride", 0}});
    FAIL() << "stride 0 was accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("stride"), std::string::npos) << e.what();
  }
  // Voting reads the last windows at the stride; a video shorter than the span is refused.
  c.size = 8;
  c.width = 4;
  torch::manual_seed(3);
  models::SuccessDetector detector(c);
  // Frames of random colours: strided and consecutive windows see different frames.
  const auto noise = torch::randint(0, 256, {20, 8, 8, 3}).to(torch::kUInt8);
  std::vector<torch::Tensor> last;
  for (int64_t i = 0; i < 5; ++i) last.push_back(models::window_ending_at(c, noise, 19 - i));
  const auto p = models::success_probability(detector, torch::stack(last));  // [5]
  EXPECT_DOUBLE_EQ(models::success_vote(detector, noise, 5),
                   (p > 0.5).to(torch::kFloat64).mean().item<double>());
  // The detector's output does depend on which frames it sees (else the vote above proves little).
  std::vector<torch::Tensor> consecutive;
  for (int64_t i = 0; i < 5; ++i) consecutive.push_back(noise.narrow(0, 17 - i, 3));
  EXPECT_FALSE(torch::allclose(p, models::success_probability(detector, torch::stack(consecutive))));
  EXPECT_THROW(models::success_vote(detector, noise.narrow(0, 0, 8)), Error);
}

// Passes every decision on to `inner` and keeps the frames it was shown.
class WatchedPolicy : public eval::Policy {
 public:
  explicit WatchedPolicy(eval::Policy& inner) : inner_(inner) {}
  const std::string& name() const override { return inner_.name(); }
  bool open_loop() const override { return inner_.open_loop(); }
  void reset(const eval::EpisodeStart& start) override {
    shown.clear();
    inner_.reset(start);
  }
  torch::Tensor act(const torch::Tensor& frames, const torch::Tensor& last_command, int64_t n) override {
    shown.push_back(frames.clone());
    return inner_.act(frames, last_command, n);
  }
  std::vector<torch::Tensor> shown;  // [k, H, W, 3] per decision

 private:
  eval::Policy& inner_;
};

// The detector's logits on the last `votes` windows of `video`, as success_vote reads them
// (the window ending at the last frame first).
torch::Tensor last_window_logits(models::SuccessDetector& detector, const torch::Tensor& video,
                                 int64_t votes) {
  std::vector<torch::Tensor> windows;
  for (int64_t i = 0; i < votes; ++i)
    windows.push_back(models::window_ending_at(detector->config(), video, video.size(0) - 1 - i));
  torch::NoGradGuard no_grad;
  detector->eval();
  return detector->forward(models::success_input(detector, torch::stack(windows)));  // [votes]
}

TEST(PolicyEval, WorldModelRunsAPolicyClosedLoop) {
  test::OneThread one;
  const fs::path reference = fs::path(DOJO_SOURCE_DIR) / "models" / "reference";
  infer::StreamingEngine::Options o;
  auto engine = infer::StreamingEngine::load(reference / "wm_posttrain", reference / "tokenizer", o);
  const auto ranges = engine.action_ranges();
  ASSERT_TRUE(ranges.contains("dojosim_robot"));
  data::ActionChunker chunker(data::slot_by_name("dojosim_robot"),
                              data::ArrayStats::from_json(ranges["dojosim_robot"], "ranges"), 4);
  torch::manual_seed(11);
  models::SuccessDetector detector(models::SuccessDetectorConfig{});  // random; shared with env
  eval::WorldModelEnvironment env("student", infer::make_student_generator(std::move(engine)),
                                  std::move(chunker), detector);
  const auto starts = test::policy_scenes(1);
  const auto owned = policies({"expert"});
  WatchedPolicy watched(*owned[0]);
  eval::PolicyEvalOptions options;
  options.steps = 2;
  options.settle_steps = 1;
  const double success = eval::run_policy_episode(watched, env, starts[0], options);
  const auto video = env.video();
  ASSERT_EQ(video.size(0), 1 + 4 * 3);
  EXPECT_EQ(video.scalar_type(), torch::kUInt8);
  // Closed loop: each decision is shown the frames the world model made since the last one (the
  // start frame as the world model shows it, then each step's 4), not the simulator's.
  ASSERT_EQ(watched.shown.size(), 2u);
  EXPECT_TRUE(torch::equal(watched.shown[0], video.narrow(0, 0, 1)));
  EXPECT_TRUE(torch::equal(watched.shown[1], video.narrow(0, 1, 4)));
  // An episode's vote is a verdict: 1 when more than half of the last windows of the video it
  // made read success, else 0.
  EXPECT_EQ(success, models::success_vote(detector, video) > 0.5 ? 1.0 : 0.0);
  // The same policy gets the same frames: the world model's noise comes from the scene's seed.
  const auto first = video.clone();
  const auto wm_shown = watched.shown;
  eval::run_policy_episode(watched, env, starts[0], options);
  EXPECT_TRUE(torch::equal(first, env.video()));
  // ... and DojoSim shows it other frames for the same commands (the scripted expert plans open
  // loop), so the checks above tell the two worlds apart.
  DojoSimEnvironment sim;
  eval::run_policy_episode(watched, sim, starts[0], options);
  ASSERT_EQ(watched.shown.size(), 2u);
  EXPECT_FALSE(torch::equal(watched.shown[1], wm_shown[1]));
  // Moving the detector's threshold (its head bias) between the logits of those last windows
  // turns the verdict: 3 of the 5 windows reading success is a success, 2 of 5 a failure. The
  // random detector reads the windows almost alike (logits within about 1e-5), so its head is
  // first sharpened until they lie about 1 apart.
  auto& head = detector->head;
  const auto original_weight = head->weight.detach().clone();
  const auto original_bias = head->bias.detach().clone();
  {
    const auto raw = last_window_logits(detector, first, models::kSuccessVotes);
    const double spread = (raw.max() - raw.min()).item<double>();
    ASSERT_GT(spread, 0.0) << "the last windows read exactly alike: " << raw;
    torch::NoGradGuard no_grad;
    head->weight.mul_(1.0 / spread);
  }
  const auto logits = std::get<0>(last_window_logits(detector, first, models::kSuccessVotes).sort(0, true));
  ASSERT_EQ(logits.size(0), models::kSuccessVotes);
  ASSERT_GT((logits.narrow(0, 0, 4) - logits.narrow(0, 1, 4)).min().item<double>(), 1e-3)
      << "the windows must read apart: " << logits;
  const auto verdict_when_reading_success = [&](int64_t windows) {  // the top `windows` logits > 0
    {
      torch::NoGradGuard no_grad;
      const double cut = 0.5 * (logits[windows - 1].item<double>() + logits[windows].item<double>());
      head->bias.copy_(original_bias - cut);
    }
    EXPECT_DOUBLE_EQ(models::success_vote(detector, first), windows / 5.0);
    return env.success();
  };
  EXPECT_EQ(verdict_when_reading_success(4), 1.0);
  EXPECT_EQ(verdict_when_reading_success(3), 1.0);
  EXPECT_EQ(verdict_when_reading_success(2), 0.0);
  EXPECT_EQ(verdict_when_reading_success(1), 0.0);
  {
    torch::NoGradGuard no_grad;
    head->weight.copy_(original_weight);
    head->bias.copy_(original_bias);
  }

  // Without a detector the world model only makes frames: the detector's training data from its
  // replays holds exactly the frames the evaluation shows, under the simulator's labels.
  auto replay_engine = infer::StreamingEngine::load(reference / "wm_posttrain", reference / "tokenizer", o);
  data::ActionChunker replay_chunker(data::slot_by_name("dojosim_robot"),
                                     data::ArrayStats::from_json(ranges["dojosim_robot"], "ranges"), 4);
  eval::WorldModelEnvironment frames_only("student", infer::make_student_generator(std::move(replay_engine)),
                                          std::move(replay_chunker), models::SuccessDetector{nullptr});
  test::TempDir tmp;
  SuccessDataOptions data_options;
  data_options.scenes = 1;
  data_options.seed = starts[0].seed;  // the scene above
  data_options.episode = options;
  std::vector<PolicySpec> expert;
  for (const auto& s : default_policy_set())
    if (s.name == "expert") expert.push_back(s);
  make_success_data(expert, data_options, tmp / "replayed.safetensors", &frames_only);
  make_success_data(expert, data_options, tmp / "simulated.safetensors");
  const auto replayed = train::SuccessData::load(tmp / "replayed.safetensors");
  const auto simulated = train::SuccessData::load(tmp / "simulated.safetensors");
  ASSERT_EQ(replayed.frames.size(0), 1);
  EXPECT_TRUE(torch::equal(replayed.frames[0], first));
  EXPECT_FALSE(torch::equal(replayed.frames, simulated.frames));
  EXPECT_TRUE(torch::equal(replayed.labels, simulated.labels));
  EXPECT_TRUE(torch::equal(replayed.simulator_frames, simulated.frames));  // both worlds kept
  EXPECT_FALSE(simulated.simulator_frames.defined());
  EXPECT_THROW(frames_only.success(), Error);
}

}  // namespace
}  // namespace dojo::recipes
