// The vision-only policies of policy evaluation (recipes/vision_policies.h): the belief controller
// does the bin task from a belief and follows the belief, not the scene; the default evaluated set
// acts on the frame it is shown and never on the scene's description; the reader learns where the
// object is; held-out scene seeds are enforced.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <fstream>

#include "core/checkpoint.h"
#include "core/error.h"
#include "models/bc_policy.h"
#include "models/scene_reader.h"
#include "recipes/dojosim_policies.h"
#include "recipes/vision_policies.h"
#include "sim/bin_belief.h"
#include "sim/policy_scenes.h"
#include "sim/world.h"
#include "test_util.h"
#include "train/reader_train.h"
#include "train/train_util.h"

namespace dojo::recipes {
namespace {

namespace fs = std::filesystem;

std::vector<double> to_vector(const torch::Tensor& t) {
  const auto d = t.to(torch::kFloat64).contiguous();
  return std::vector<double>(d.data_ptr<double>(), d.data_ptr<double>() + d.numel());
}

// One episode (64 frames acting, 12 settling, as policy eval's) of the belief controller in
// DojoSim, its belief made from the simulator's state by `believe`; returns bin success.
double belief_episode(const eval::EpisodeStart& start,
                      const std::function<sim::BinBelief(const sim::World&)>& believe) {
  DojoSimEnvironment env;
  env.reset(start);
  sim::BeliefControllerOptions o;
  o.start_command = to_vector(start.command);
  o.control_dt = sim::SceneSpec{}.timestep * sim::SceneSpec{}.substeps;
  sim::BeliefBinController controller(o);
  std::vector<double> command;
  for (int step = 0; step < 64; ++step) {
    sim::BinBelief belief;
    if (controller.plans_at(step)) belief = believe(env.world());
    command = controller.act(belief, step);
    env.step(torch::tensor(std::vector<float>(command.begin(), command.end())).unsqueeze(0));
  }
  for (int step = 0; step < 12; ++step)
    env.step(torch::tensor(std::vector<float>(command.begin(), command.end())).unsqueeze(0));
  return env.success();
}

TEST(BinBelief, ValuesRoundTripWithTheRollModuloPi) {
  sim::BinBelief b;
  b.object_x = -0.05;
  b.object_y = 0.02;
  b.roll = 2.0;  // the fingers are symmetric: 2.0 - pi reads back
  const auto back = sim::BinBelief::from_values(b.to_values());
  EXPECT_NEAR(back.object_x, -0.05, 1e-12);
  EXPECT_NEAR(back.roll, 2.0 - M_PI, 1e-9);
  EXPECT_FALSE(b.object_in_bin());
  b.object_x = b.bin_x + 0.03;
  b.object_y = b.bin_y - 0.03;
  EXPECT_TRUE(b.object_in_bin());
  try {
    sim::BinBelief::from_values({1, 2, 3});
    FAIL() << "three values accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("expected 8 values, got 3"), std::string::npos);
  }
}

// With the simulator's own belief the controller does the task; with the object believed 12 cm
// away from where it is, it fails everywhere: it acts on its belief alone.
TEST(BeliefBinController, DoesTheTaskFromATrueBeliefAndFollowsAWrongOne) {
  test::OneThread one;
  const auto starts = test::policy_scenes(6);
  double right = 0, wrong = 0;
  for (const auto& start : starts) {
    right += belief_episode(start, [](const sim::World& w) { return sim::true_bin_belief(w); });
    wrong += belief_episode(start, [](const sim::World& w) {
      auto b = sim::true_bin_belief(w);
      b.object_x += b.object_x > 0 ? -0.12 : 0.12;
      return b;
    });
  }
  EXPECT_GE(right, 5.0) << "the true belief succeeded in " << right << " of 6 scenes";
  EXPECT_EQ(wrong, 0.0);
}

// Every family of the default evaluated set acts on the frame it is shown: the same frame with
// another scene's description gives the same commands, another frame other commands. A scripted
// planner, which reads the description, fails the same check (the test can tell them apart).
TEST(VisionPolicies, FollowTheFrameNotTheScene) {
  test::OneThread one;
  test::TempDir tmp;
  torch::manual_seed(3);
  save_checkpoint(train::step_snapshot_dir(tmp / "bc", 0), models::bc_policy_checkpoint(*models::BcPolicy()));
  save_checkpoint(train::step_snapshot_dir(tmp / "reader", 0),
                  models::scene_reader_checkpoint(*models::SceneReader()));
  const auto specs = vision_policy_set(tmp / "bc", tmp / "reader");
  ASSERT_EQ(specs.size(), 1u + 1u + 6u);  // bc-0, reader-0 and the knob variants of the last reader
  EXPECT_EQ(specs[0].name, "bc-0");
  EXPECT_EQ(specs[1].name, "reader-0");
  const auto starts = test::policy_scenes(2);
  auto a = starts[0], a_described_as_b = starts[0], b_shown = starts[1];
  a_described_as_b.scene = starts[1].scene;
  b_shown.scene = a.scene;  // only the frame differs
  b_shown.seed = a.seed;    // only the frame differs
  b_shown.command = a.command;
  const auto commands = [](eval::Policy& p, const eval::EpisodeStart& s) {
    p.reset(s);
    return p.act(s.frame.unsqueeze(0), s.command, 4);  // [4, 6]
  };
  for (const auto& spec : specs) {
    auto policy = spec.checkpoint.empty()
                      ? make_reader_policy(spec)
                      : eval::make_bc_policy(spec.name, models::load_bc_policy(spec.checkpoint));
    EXPECT_FALSE(policy->open_loop()) << spec.name;
    const auto seen = commands(*policy, a);
    EXPECT_TRUE(torch::equal(seen, commands(*policy, a_described_as_b))) << spec.name << " read the scene";
    EXPECT_FALSE(torch::equal(seen, commands(*policy, b_shown))) << spec.name << " ignored the frame";
  }
  const auto expert = make_scripted_policy(default_policy_set().front());
  EXPECT_FALSE(torch::equal(commands(*expert, a), commands(*expert, a_described_as_b)));
}

TEST(VisionPolicies, ReaderLearnsWhereTheObjectIs) {
  test::OneThread one;
  test::TempDir tmp;
  ReaderDataOptions o;
  o.episodes = 32;
  o.frames = 24;
  o.every = 2;
  o.heldout_fraction = 0.25;
  make_reader_data(o, tmp / "readings.safetensors");
  const auto data = train::SceneReadings::load(tmp / "readings.safetensors");
  EXPECT_EQ(data.frames.size(0), 32 * 12);
  EXPECT_EQ(data.values.size(1), sim::BinBelief::kValues);
  train::ReaderTrainJob job;
  job.data = tmp / "readings.safetensors";
  job.out = tmp / "reader";
  job.steps = 500;
  job.batch_size = 32;
  job.snapshots = {0};
  const auto r = train::run_reader_training(job);
  ASSERT_EQ(r.snapshots.size(), 2u);
  auto untrained = models::load_scene_reader(r.snapshots.front());
  const auto before = train::reader_errors(untrained, data, data.heldout);
  EXPECT_EQ(r.heldout.frames, 8 * 12);
  // Where the object is, on episodes it never saw: under an untrained reader's error (which
  // reads every frame as the training mean; the bin moves too little for that to tell). 500 steps
  // on 24 episodes: 8.5 -> 6.1 cm; the default run (144 episodes, 2000 steps) reads 3.4 cm.
  EXPECT_LT(r.heldout.object_cm, 0.8 * before.object_cm) << before.object_cm;
}

TEST(VisionPolicies, HeldOutSeedsAndBadEntries) {
  EXPECT_NO_THROW(check_disjoint_seeds({{"a", 7000, 30}, {"b", 9000, 24}, {"c", 7030, 5}}));
  try {
    check_disjoint_seeds(
        {{"the evaluation's scenes", 9010, 4}, {"the success detector's episodes", 9000, 24}});
    FAIL() << "overlapping seeds accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("the evaluation's scenes (seeds 9010-9013) and the success "
                                         "detector's episodes (seeds 9000-9023) share scenes"),
              std::string::npos)
        << e.what();
  }
  test::TempDir tmp;
  save_checkpoint(tmp / "reader", models::scene_reader_checkpoint(*models::SceneReader()));
  const auto refused = [&](const std::string& entry, const std::string& expected) {
    std::ofstream(tmp / "set.json") << R"({"policies": [)" << entry << "]}";
    try {
      read_policy_set(tmp / "set.json");
      ADD_FAILURE() << entry << " accepted";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(expected), std::string::npos) << e.what();
    }
  };
  refused(R"({"name": "r", "reader": "reader", "quality": {"speeed": 1}})", "unknown reader knob 'speeed'");
  refused(R"({"name": "r", "reader": "reader", "behavior": "idle"})", "give one of");
  refused(R"({"name": "r", "reader": "nowhere"})", "policies[0]: no checkpoint at");
  std::ofstream(tmp / "set.json")
      << R"({"policies": [{"name": "r", "reader": "reader", "quality": {"speed": 0.5}}]})";
  const auto set = read_policy_set(tmp / "set.json");
  ASSERT_EQ(set.size(), 1u);
  EXPECT_FALSE(set[0].scripted());
  EXPECT_EQ(set[0].reader, tmp / "reader");
  EXPECT_EQ(make_reader_policy(set[0])->name(), "r");
}

}  // namespace
}  // namespace dojo::recipes
