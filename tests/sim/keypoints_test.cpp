// Image keypoints from the simulator: the projection agrees with the renderer, and episodes and
// datasets carry them.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cmath>

#include "data/episode_store.h"
#include "sim/episode.h"
#include "sim/generate.h"
#include "sim/renderer.h"
#include "sim/world.h"
#include "test_util.h"

namespace dojo::sim {
namespace {

// Centroid (u, v in [0, 1]) of the pixels that differ between two renders of the same size.
std::array<double, 2> changed_centroid(const std::vector<uint8_t>& a, const std::vector<uint8_t>& b,
                                       int width, int height) {
  double su = 0, sv = 0, n = 0;
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      const size_t i = (static_cast<size_t>(y) * width + x) * 3;
      if (std::abs(a[i] - b[i]) + std::abs(a[i + 1] - b[i + 1]) + std::abs(a[i + 2] - b[i + 2]) > 30)
        su += x + 0.5, sv += y + 0.5, ++n;
    }
  EXPECT_GT(n, 10) << "the object should cover some pixels";
  return {su / n / width, sv / n / height};
}

// An object moved to a known point appears where World::project says, within a pixel or two.
TEST(SimKeypoints, ProjectionMatchesTheRenderer) {
  SceneSampling sampling;
  sampling.width = 320;
  sampling.height = 240;
  sampling.min_objects = sampling.max_objects = 1;
  for (Embodiment e : {Embodiment::kRobot, Embodiment::kHuman}) {
    World w(sample_scene(e, sampling, 3));
    Renderer renderer;
    for (const Vec3 p : {Vec3{-0.2, 0.2, 0.15}, Vec3{0.0, 0.35, 0.05}, Vec3{-0.1, 0.1, 0.15}}) {
      w.set_object_pose(0, {5.0, 5.0, -5.0});  // far out of view
      const auto empty = renderer.render(w);
      w.set_object_pose(0, p);
      const auto with_object = renderer.render(w);
      const auto c = changed_centroid(empty, with_object, sampling.width, sampling.height);
      const auto projected = w.project(p);
      ASSERT_TRUE(projected.in_view);
      EXPECT_NEAR(projected.u * sampling.width, c[0] * sampling.width, 2.0)
          << p[0] << " " << p[1] << " " << p[2];
      EXPECT_NEAR(projected.v * sampling.height, c[1] * sampling.height, 2.0)
          << p[0] << " " << p[1] << " " << p[2];
    }
    EXPECT_FALSE(w.project({0.0, 0.0, 5.0}).in_view);  // above the camera, out of the image
  }
}

TEST(SimKeypoints, EpisodesAndDatasetsCarryThem) {
  test::TempDir tmp;
  GenerateOptions g;
  g.episodes = 2;
  g.frames = 6;
  g.workers = 1;
  g.val_fraction = 0;
  generate_dataset(tmp / "robot", g);
  const auto store = data::EpisodeStore::open(tmp / "robot");
  EXPECT_EQ(store.info().keypoint_names, (std::vector<std::string>{"gripper", "wrist", "elbow"}));
  const auto arrays = store.load_arrays(0);
  ASSERT_TRUE(arrays.keypoints.defined());
  EXPECT_EQ(arrays.keypoints.sizes(), (std::vector<int64_t>{6, 9}));
  const auto kp = arrays.keypoints.view({6, 3, 3});
  // The gripper is in view at the start of a bin-task episode, inside the image.
  EXPECT_EQ(kp[0][0][2].item<float>(), 1.f);
  // Keypoints in view lie inside the image; the others (the elbow can leave the frame) do not.
  const auto in_view = kp.select(2, 2).gt(0.5);
  const auto uv = kp.narrow(2, 0, 2);
  EXPECT_GE(uv.select(2, 0).masked_select(in_view).min().item<float>(), 0.f);
  EXPECT_LE(uv.select(2, 0).masked_select(in_view).max().item<float>(), 1.f);
  EXPECT_GE(uv.select(2, 1).masked_select(in_view).min().item<float>(), 0.f);
  EXPECT_LE(uv.select(2, 1).masked_select(in_view).max().item<float>(), 1.f);

  g.embodiment = "human";
  generate_dataset(tmp / "human", g);
  EXPECT_EQ(data::EpisodeStore::open(tmp / "human").info().keypoint_names,
            (std::vector<std::string>{"palm", "index", "thumb"}));
}

}  // namespace
}  // namespace dojo::sim
