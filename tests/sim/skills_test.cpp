#include "sim/skills.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>

#include "core/error.h"
#include "core/json_file.h"
#include "sim/episode.h"
#include "sim/task.h"

namespace dojo::sim {
namespace {

double mean_success(const std::string& quality, int episodes) {
  double sum = 0.0;
  for (int i = 0; i < episodes; ++i) {
    SceneSampling opt;
    opt.min_objects = opt.max_objects = 2;
    EpisodeSpec e;
    e.scene = sample_scene(Embodiment::kRobot, opt, 100 + i);
    e.controller = default_controller(Embodiment::kRobot);
    e.controller.robot.quality = PolicyQuality::preset(quality);
    e.num_steps = 130;
    e.seed = i;
    e.render = false;
    sum += run_episode(e).success;
  }
  return sum / episodes;
}

TEST(SimSkills, PolicyQualityGivesClearlyDifferentSuccess) {
  const double expert = mean_success("expert", 8);
  const double poor = mean_success("poor", 8);
  EXPECT_GT(expert, 0.8);
  EXPECT_LT(poor, 0.4);
  EXPECT_GT(expert - poor, 0.45);
}

TEST(SimSkills, PresetsAndNamesParse) {
  EXPECT_EQ(PolicyQuality::preset("expert").noise_std, 0.0);
  EXPECT_GT(PolicyQuality::preset("poor").miss_prob, PolicyQuality::preset("medium").miss_prob);
  EXPECT_THROW(PolicyQuality::preset("legendary"), UsageError);
  for (HumanSkill s : all_human_skills()) EXPECT_EQ(parse_human_skill(to_string(s)), s);
  EXPECT_THROW(parse_human_skill("juggle"), UsageError);
  EXPECT_EQ(parse_robot_behavior("reach_miss"), RobotBehavior::kReachMiss);
  EXPECT_THROW(parse_robot_behavior("dance"), UsageError);
}

// Runs one human skill (no chaining) on a fixed 3-object scene and returns the world afterwards.
struct SkillRun {
  std::unique_ptr<World> world;
  std::vector<ObjectPose> initial;
  double max_lift = 0.0;   // highest lowest-point of any object
  double hand_travel = 0;  // path length of the commanded palm position
  std::string text;
  nlohmann::json info;
};

SkillRun run_skill(HumanSkill skill, uint64_t scene_seed, int steps = 70) {
  SceneSampling opt;
  opt.min_objects = opt.max_objects = 3;
  SkillRun r;
  r.world = std::make_unique<World>(sample_scene(Embodiment::kHuman, opt, scene_seed));
  World& w = *r.world;
  HumanSkillOptions o;
  o.skills = {skill};
  o.chain = false;
  o.target_object = 0;
  auto c = make_human_controller(w, o, scene_seed);
  w.hold(5);
  r.initial = w.object_poses();
  std::vector<double> prev = w.last_command();
  for (int t = 0; t < steps; ++t) {
    const std::vector<double> cmd = c->act(w, t);
    r.hand_travel += std::hypot(cmd[0] - prev[0], cmd[1] - prev[1], cmd[2] - prev[2]);
    prev = cmd;
    w.step(cmd);
    for (int i = 0; i < w.num_objects(); ++i) r.max_lift = std::max(r.max_lift, w.object_z_range(i)[0]);
  }
  w.hold(10);
  r.text = c->task_text();
  r.info = c->describe();
  return r;
}

TEST(SimSkills, EveryHumanSkillRunsAndMovesTheHand) {
  for (HumanSkill skill : all_human_skills()) {
    const SkillRun r = run_skill(skill, 21);
    EXPECT_GT(r.hand_travel, 0.1) << to_string(skill);
    EXPECT_FALSE(r.text.empty());
    ASSERT_EQ(r.info["skills"].size(), 1u) << to_string(skill);
    const std::string name = object_description(r.world->spec().objects[0]);
    EXPECT_NE(r.text.find(name), std::string::npos) << r.text << " / " << name;
  }
}

TEST(SimSkills, HumanSkillsHaveTheirPhysicalEffect) {
  // Scene 21 has three objects; object 0 is the target.
  const SkillRun push = run_skill(HumanSkill::kPush, 21);
  EXPECT_GT(object_displacement(push.initial[0], push.world->object_pose(0)), 0.03) << push.text;
  const SkillRun pick = run_skill(HumanSkill::kPickPlace, 21);
  EXPECT_GT(pick.max_lift, 0.04) << pick.text;
  const SkillRun reach = run_skill(HumanSkill::kReach, 21);
  for (int i = 0; i < 3; ++i)
    EXPECT_LT(object_displacement(reach.initial[i], reach.world->object_pose(i)), 0.005);
  const SkillRun pat = run_skill(HumanSkill::kPat, 21);
  EXPECT_LT(pat.max_lift, 0.01);
}

TEST(SimSkills, RobotCounterfactualBehaviours) {
  SceneSampling opt;
  opt.min_objects = opt.max_objects = 1;
  auto run = [&](RobotBehavior b) {
    EpisodeSpec e;
    e.scene = sample_scene(Embodiment::kRobot, opt, 31);
    e.controller = default_controller(Embodiment::kRobot);
    e.controller.robot.behavior = b;
    e.num_steps = 60;
    e.render = false;
    e.seed = 2;
    return run_episode(e);
  };
  const EpisodeRecord pat = run(RobotBehavior::kPat);
  EXPECT_EQ(pat.success, 0.0);
  EXPECT_LT(pat.meta["object_outcomes"][0]["displacement"].get<double>(), 0.02);
  const EpisodeRecord miss = run(RobotBehavior::kReachMiss);
  EXPECT_EQ(miss.success, 0.0);
  EXPECT_LT(miss.meta["object_outcomes"][0]["displacement"].get<double>(), 0.02);
  const EpisodeRecord push = run(RobotBehavior::kPush);
  EXPECT_GT(push.meta["object_outcomes"][0]["displacement"].get<double>(), 0.03);
  const EpisodeRecord random = run(RobotBehavior::kRandomMotion);
  double spread = 0.0;
  for (const auto& a : random.actions)
    spread = std::max(spread, std::fabs(double(a[0]) - random.actions[0][0]));
  EXPECT_GT(spread, 0.2);  // the base actually swings around
  for (const EpisodeRecord* r : {&pat, &miss, &push, &random})
    EXPECT_FALSE(r->meta["task"].get<std::string>().empty());
}

// Teleoperation play is held keys: between the home jumps, at most two joints move per step, each
// by at most its key's rate times the control step, and full-rate ramps of several steps occur.
// The rates are read from the teleoperation page's mapping, so the play data and the page cannot
// drift apart.
TEST(SimSkills, TeleopPlayMovesLikeHeldKeys) {
  const auto mapping = read_json_file(std::filesystem::path(DOJO_SOURCE_DIR) / "src" / "serve" / "pages" /
                                      "dojosim_robot.mapping.json");
  ASSERT_EQ(mapping.at("dims").size(), 6u);
  double kRates[6];
  for (int d = 0; d < 6; ++d) kRates[d] = mapping["dims"][d].at("rate").get<double>();
  int full_rate_runs = 0, homes = 0;
  double fastest[6] = {0, 0, 0, 0, 0, 0};  // each joint's largest step outside the home jumps
  for (uint64_t seed = 0; seed < 12; ++seed) {
    EpisodeSpec e;
    e.scene = sample_scene(Embodiment::kRobot, {}, 40 + seed);
    e.controller = default_controller(Embodiment::kRobot);
    e.controller.robot.behavior = RobotBehavior::kTeleopPlay;
    e.num_steps = 64;
    e.render = false;
    e.seed = seed;
    const EpisodeRecord r = run_episode(e);
    EXPECT_EQ(r.meta["controller"]["behavior"], "teleop_play");
    const double dt = 0.1;
    int run = 0;
    for (size_t t = 1; t < r.actions.size(); ++t) {
      int moving = 0, full = 0;
      for (int d = 0; d < 6; ++d) {
        const double delta = std::fabs(double(r.actions[t][d]) - r.actions[t - 1][d]);
        if (delta > 1e-5) ++moving;
        if (std::fabs(delta - kRates[d] * dt) < 1e-4) ++full;
      }
      bool jump = false;
      for (int d = 0; d < 6; ++d)
        jump |= std::fabs(double(r.actions[t][d]) - r.actions[t - 1][d]) > kRates[d] * dt + 1e-4;
      if (jump) {
        ++homes;
        run = 0;
        continue;
      }
      EXPECT_LE(moving, 2) << "seed " << seed << " step " << t;
      for (int d = 0; d < 6; ++d)
        fastest[d] = std::max(fastest[d], std::fabs(double(r.actions[t][d]) - r.actions[t - 1][d]));
      run = full > 0 ? run + 1 : 0;
      if (run == 5) ++full_rate_runs;
    }
  }
  EXPECT_GE(full_rate_runs, 4);
  EXPECT_GE(homes, 1);
  // Every key is held at full rate somewhere, and moves its joint at exactly the page's rate.
  for (int d = 0; d < 6; ++d)
    EXPECT_NEAR(fastest[d], kRates[d] * 0.1, 1e-4) << mapping["dims"][d].at("name").get<std::string>();
}

TEST(SimSkills, ControllersRejectTheWrongEmbodiment) {
  World human(sample_scene(Embodiment::kHuman, {}, 0));
  World robot(sample_scene(Embodiment::kRobot, {}, 0));
  EXPECT_THROW(make_robot_controller(human, {}, 0), Error);
  EXPECT_THROW(make_human_controller(robot, {}, 0), Error);
}

}  // namespace
}  // namespace dojo::sim
