#include "sim/scene.h"

#include <gtest/gtest.h>

#include <set>

#include <nlohmann/json.hpp>

#include "core/error.h"
#include "sim/world.h"

namespace dojo::sim {
namespace {

TEST(SimScene, SamplingIsDeterministicAndSeedDependent) {
  for (Embodiment e : {Embodiment::kHuman, Embodiment::kRobot}) {
    const SceneSpec a = sample_scene(e, {}, 42), b = sample_scene(e, {}, 42), c = sample_scene(e, {}, 43);
    EXPECT_EQ(to_json(a).dump(), to_json(b).dump());
    EXPECT_EQ(build_mjcf(a), build_mjcf(b));
    EXPECT_NE(to_json(a).dump(), to_json(c).dump());
  }
}

TEST(SimScene, ManySeedsBuildAndLoadForBothEmbodiments) {
  std::set<int> human_shapes, human_backgrounds, robot_backgrounds;
  for (uint64_t seed = 0; seed < 40; ++seed) {
    for (Embodiment e : {Embodiment::kHuman, Embodiment::kRobot}) {
      const SceneSpec spec = sample_scene(e, {}, seed);
      ASSERT_NO_THROW(World world(spec)) << "seed " << seed << " " << to_string(e);
      (e == Embodiment::kHuman ? human_backgrounds : robot_backgrounds).insert(spec.background);
      EXPECT_EQ(spec.bin.enabled || e == Embodiment::kHuman, true);
      for (const auto& o : spec.objects) {
        if (e == Embodiment::kHuman) human_shapes.insert(static_cast<int>(o.shape));
        if (e == Embodiment::kRobot) {
          EXPECT_TRUE(in_robot_set(o)) << object_description(o);
        }
      }
    }
  }
  EXPECT_EQ(human_shapes.size(), static_cast<size_t>(kNumShapes));  // the wide set covers every shape
  for (int b : human_backgrounds) EXPECT_LT(b, kNumTrainBackgrounds);
  EXPECT_GE(human_backgrounds.size(), 5u);
  for (int b : robot_backgrounds) EXPECT_LT(b, 2);  // the robot data is narrow
}

TEST(SimScene, SplitsDrawFromTheirOwnSets) {
  SceneSampling novel;
  novel.backgrounds = BackgroundSplit::kNovel;
  SceneSampling ood;
  ood.object_set = ObjectSet::kHumanOnly;
  ood.min_objects = 2;
  int ood_objects = 0;
  for (uint64_t seed = 0; seed < 20; ++seed) {
    const SceneSpec n = sample_scene(Embodiment::kRobot, novel, seed);
    EXPECT_GE(n.background, kNumTrainBackgrounds);
    const SceneSpec o = sample_scene(Embodiment::kRobot, ood, seed);
    for (const auto& obj : o.objects) {
      EXPECT_FALSE(in_robot_set(obj)) << object_description(obj);
      ++ood_objects;
    }
    ASSERT_NO_THROW(World w(o));
    ASSERT_NO_THROW(World w(n));
  }
  EXPECT_GT(ood_objects, 20);
}

TEST(SimScene, ObjectsDoNotOverlapAndAvoidTheBin) {
  SceneSampling opt;
  opt.min_objects = opt.max_objects = 4;
  for (uint64_t seed = 0; seed < 20; ++seed) {
    const SceneSpec s = sample_scene(Embodiment::kHuman, opt, seed);
    for (size_t i = 0; i < s.objects.size(); ++i) {
      for (size_t j = i + 1; j < s.objects.size(); ++j) {
        const double d =
            std::hypot(s.objects[i].pos[0] - s.objects[j].pos[0], s.objects[i].pos[1] - s.objects[j].pos[1]);
        EXPECT_GT(d, object_footprint_radius(s.objects[i]) + object_footprint_radius(s.objects[j]));
      }
      if (s.bin.enabled) {
        const bool inside = std::fabs(s.objects[i].pos[0] - s.bin.center[0]) < s.bin.half_x &&
                            std::fabs(s.objects[i].pos[1] - s.bin.center[1]) < s.bin.half_y;
        EXPECT_FALSE(inside);
      }
    }
  }
}

TEST(SimScene, JsonRoundTripReproducesTheMjcf) {
  for (Embodiment e : {Embodiment::kHuman, Embodiment::kRobot}) {
    const SceneSpec s = sample_scene(e, {}, 7);
    const SceneSpec back = scene_from_json(nlohmann::json::parse(to_json(s).dump()));
    EXPECT_EQ(build_mjcf(back), build_mjcf(s));
  }
  nlohmann::json broken = to_json(sample_scene(Embodiment::kRobot, {}, 1));
  broken.erase("camera");
  EXPECT_THROW(scene_from_json(broken), Error);
}

TEST(SimScene, BadInputsGiveClearErrors) {
  SceneSampling bad;
  bad.min_objects = 3;
  bad.max_objects = 1;
  EXPECT_THROW(sample_scene(Embodiment::kHuman, bad, 0), UsageError);
  EXPECT_THROW(parse_embodiment("alien"), UsageError);
  SceneSpec s = sample_scene(Embodiment::kRobot, {}, 0);
  s.background = 99;
  EXPECT_THROW(build_mjcf(s), Error);
  // A geometry MuJoCo rejects surfaces as a dojo::Error carrying MuJoCo's message.
  SceneSpec neg = sample_scene(Embodiment::kRobot, {}, 0);
  ASSERT_FALSE(neg.objects.empty());
  neg.objects[0].mass = -1.0;
  try {
    World w(neg);
    FAIL() << "expected a compile error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("MJCF"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace dojo::sim
