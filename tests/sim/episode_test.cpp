#include "sim/episode.h"

#include <gtest/gtest.h>

#include <cmath>

#include "core/error.h"

namespace dojo::sim {
namespace {

EpisodeSpec robot_spec(int steps, bool render) {
  EpisodeSpec e;
  SceneSampling opt;
  opt.min_objects = opt.max_objects = 1;
  e.scene = sample_scene(Embodiment::kRobot, opt, 12);
  e.controller = default_controller(Embodiment::kRobot);
  e.num_steps = steps;
  e.seed = 12;
  e.render = render;
  return e;
}

TEST(SimEpisode, RobotRecordIsAlignedAndComplete) {
  const EpisodeRecord r = run_episode(robot_spec(70, true));
  ASSERT_EQ(r.frames.size(), 70u);
  ASSERT_EQ(r.actions.size(), 70u);
  ASSERT_EQ(r.states.size(), 70u);
  ASSERT_EQ(r.hidden_motion.size(), 70u);
  EXPECT_EQ(r.frames[0].size(), 64u * 64u * 3u);
  EXPECT_EQ(r.actions[0].size(), 6u);
  EXPECT_EQ(r.states[0].size(), 6u);
  EXPECT_EQ(r.hidden_motion[0].size(), 5u);
  EXPECT_DOUBLE_EQ(r.success, 1.0);  // the expert puts a single cube/cylinder in the bin
  EXPECT_EQ(r.meta["embodiment"], "robot");
  EXPECT_EQ(r.meta["fps"].get<double>(), 10.0);
  EXPECT_EQ(r.meta["action_names"].size(), 6u);
  EXPECT_FALSE(r.meta["ood_objects"].get<bool>());
  EXPECT_NE(r.meta["task"].get<std::string>().find("bin"), std::string::npos);
  // action[t] is executed during step t, so state[t+1] lands close to it.
  double err = 0;
  for (size_t t = 0; t + 1 < r.actions.size(); ++t) {
    for (int j = 0; j < 5; ++j) err += std::fabs(r.states[t + 1][j] - r.actions[t][j]);
  }
  EXPECT_LT(err / (69 * 5), 0.02);
  // ...and frames change while the arm moves.
  EXPECT_NE(r.frames[0], r.frames[30]);
}

TEST(SimEpisode, HumanEpisodesHaveNoActionsOnlyHiddenMotion) {
  EpisodeSpec e;
  e.scene = sample_scene(Embodiment::kHuman, {}, 4);
  e.controller = default_controller(Embodiment::kHuman);
  e.num_steps = 30;
  e.seed = 4;
  const EpisodeRecord r = run_episode(e);
  EXPECT_EQ(r.frames.size(), 30u);
  EXPECT_TRUE(r.actions.empty());
  EXPECT_TRUE(r.states.empty());
  ASSERT_EQ(r.hidden_motion.size(), 30u);
  EXPECT_EQ(r.hidden_motion[0].size(), 6u);
  EXPECT_TRUE(std::isnan(r.success));
  EXPECT_TRUE(r.meta["success"].is_null());
  EXPECT_TRUE(r.meta["action_names"].empty());
  EXPECT_FALSE(r.meta["task"].get<std::string>().empty());
  EXPECT_EQ(r.meta["hidden_motion_names"][0], "hand_x");
  ASSERT_GE(r.meta["skills"].size(), 1u);
  EXPECT_NO_THROW(parse_human_skill(r.meta["skills"][0].get<std::string>()));
}

TEST(SimEpisode, SameSpecGivesIdenticalBytes) {
  for (Embodiment emb : {Embodiment::kHuman, Embodiment::kRobot}) {
    EpisodeSpec e;
    e.scene = sample_scene(emb, {}, 77);
    e.controller = default_controller(emb);
    if (emb == Embodiment::kRobot) e.controller.robot.quality = PolicyQuality::preset("medium");
    e.num_steps = 25;
    e.seed = 5;
    const EpisodeRecord a = run_episode(e), b = run_episode(e);
    EXPECT_EQ(a.frames, b.frames);
    EXPECT_EQ(a.actions, b.actions);
    EXPECT_EQ(a.states, b.states);
    EXPECT_EQ(a.hidden_motion, b.hidden_motion);
    EXPECT_EQ(a.meta.dump(), b.meta.dump());
    e.seed = 6;  // a different controller seed changes the motion
    EXPECT_NE(run_episode(e).hidden_motion, a.hidden_motion);
  }
}

TEST(SimEpisode, RenderingCanBeSwitchedOff) {
  const EpisodeRecord r = run_episode(robot_spec(20, false));
  EXPECT_TRUE(r.frames.empty());
  EXPECT_EQ(r.actions.size(), 20u);
}

TEST(SimEpisode, RejectsMismatchedControllerAndBadLengths) {
  EpisodeSpec e = robot_spec(10, false);
  e.controller = default_controller(Embodiment::kHuman);
  EXPECT_THROW(run_episode(e), Error);
  e = robot_spec(0, false);
  EXPECT_THROW(run_episode(e), Error);
}

TEST(SimEpisode, MetaMarksEvaluationSplits) {
  EpisodeSpec e = robot_spec(5, false);
  SceneSampling ood;
  ood.object_set = ObjectSet::kHumanOnly;
  ood.backgrounds = BackgroundSplit::kNovel;
  e.scene = sample_scene(Embodiment::kRobot, ood, 3);
  const EpisodeRecord r = run_episode(e);
  EXPECT_TRUE(r.meta["ood_objects"].get<bool>());
  EXPECT_TRUE(r.meta["novel_background"].get<bool>());
}

}  // namespace
}  // namespace dojo::sim
