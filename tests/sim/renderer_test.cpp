#include "sim/renderer.h"

#include <gtest/gtest.h>

#include <cmath>
#include <thread>

#include "sim/world.h"

namespace dojo::sim {
namespace {

double stddev(const std::vector<uint8_t>& img) {
  double sum = 0, sq = 0;
  for (uint8_t v : img) {
    sum += v;
    sq += double(v) * v;
  }
  const double n = img.size();
  return std::sqrt(std::max(0.0, sq / n - (sum / n) * (sum / n)));
}

// Pixels whose chromaticity matches `rgba` (shading changes brightness, not hue much).
double fraction_of_color(const std::vector<uint8_t>& img, const Rgba& rgba) {
  const double cs = rgba[0] + rgba[1] + rgba[2];
  int hits = 0;
  const int n = static_cast<int>(img.size() / 3);
  for (int i = 0; i < n; ++i) {
    const double r = img[3 * i], g = img[3 * i + 1], b = img[3 * i + 2], s = r + g + b;
    if (s < 60) continue;
    if (std::fabs(r / s - rgba[0] / cs) < 0.025 && std::fabs(g / s - rgba[1] / cs) < 0.025) ++hits;
  }
  return double(hits) / n;
}

int changed_pixels(const std::vector<uint8_t>& a, const std::vector<uint8_t>& b) {
  int n = 0;
  for (size_t i = 0; i < a.size(); i += 3) {
    if (std::abs(a[i] - b[i]) + std::abs(a[i + 1] - b[i + 1]) + std::abs(a[i + 2] - b[i + 2]) > 30) ++n;
  }
  return n;
}

TEST(SimRenderer, ImagesHaveTheRequestedSizeAndContent) {
  Renderer r;
  for (Embodiment e : {Embodiment::kHuman, Embodiment::kRobot}) {
    for (auto [w, h] : {std::pair{64, 64}, std::pair{320, 240}, std::pair{640, 480}}) {
      SceneSampling opt;
      opt.width = w;
      opt.height = h;
      World world(sample_scene(e, opt, 3));
      const std::vector<uint8_t> img = r.render(world);
      ASSERT_EQ(img.size(), static_cast<size_t>(w * h * 3));
      EXPECT_GT(stddev(img), 15.0) << to_string(e) << " " << w << "x" << h;
    }
  }
}

TEST(SimRenderer, HumanRendersShowSkin) {
  Renderer r;
  for (uint64_t seed = 0; seed < 4; ++seed) {
    SceneSpec spec = sample_scene(Embodiment::kHuman, {}, seed);
    spec.background = 1;  // grey table: nothing else is skin-coloured
    spec.skin = {0.87, 0.62, 0.48, 1};
    for (auto& o : spec.objects) o.rgba = {0.2, 0.3, 0.8, 1};
    World world(spec);
    world.hold(2);
    EXPECT_GT(fraction_of_color(r.render(world), spec.skin), 0.02) << "seed " << seed;
    // Move the hand out of the camera's view: the skin disappears.
    for (int i = 0; i < 10; ++i) world.step({0.45, -0.5, 0.5, 0.0, 0.0, 0.0});
    EXPECT_LT(fraction_of_color(r.render(world), spec.skin), 0.01) << "seed " << seed;
  }
}

TEST(SimRenderer, RobotArmIsVisibleAndMoves) {
  Renderer r;
  World world(sample_scene(Embodiment::kRobot, {}, 2));
  const std::vector<uint8_t> home = r.render(world);
  // Swing the arm over the middle of the table.
  std::vector<double> c = world.last_command();
  c[0] += 0.5;
  for (int i = 0; i < 10; ++i) world.step(c);
  const std::vector<uint8_t> moved = r.render(world);
  EXPECT_GT(changed_pixels(home, moved), 64 * 64 / 30);
}

TEST(SimRenderer, RenderingIsDeterministic) {
  Renderer a, b;
  const SceneSpec spec = sample_scene(Embodiment::kHuman, {}, 5);
  World w1(spec), w2(spec);
  w1.hold(3);
  w2.hold(3);
  const std::vector<uint8_t> x = a.render(w1);
  EXPECT_EQ(x, a.render(w1));
  EXPECT_EQ(x, b.render(w2));
  EXPECT_EQ(x, a.render(w2));
}

TEST(SimRenderer, BackgroundsLookDifferent) {
  Renderer r;
  SceneSpec spec = sample_scene(Embodiment::kRobot, {}, 1);
  std::vector<std::vector<uint8_t>> images;
  for (int b = 0; b < kNumBackgrounds; ++b) {
    spec.background = b;
    World w(spec);
    images.push_back(r.render(w));
  }
  for (int i = 0; i < kNumBackgrounds; ++i) {
    for (int j = i + 1; j < kNumBackgrounds; ++j)
      EXPECT_GT(changed_pixels(images[i], images[j]), 64 * 64 / 5) << i << " " << j;
  }
}

TEST(SimRenderer, WorksOnAnotherThreadAndWithSeveralRenderers) {
  const SceneSpec spec = sample_scene(Embodiment::kRobot, {}, 8);
  World main_world(spec);
  Renderer here;
  const std::vector<uint8_t> expected = here.render(main_world);
  std::vector<uint8_t> from_thread;
  std::thread t([&] {
    World w(spec);
    Renderer there;
    from_thread = there.render(w);
  });
  t.join();
  EXPECT_EQ(from_thread, expected);
  // The first renderer still works after another context was current on this thread.
  Renderer other;
  World second(sample_scene(Embodiment::kHuman, {}, 8));
  other.render(second);
  EXPECT_EQ(here.render(main_world), expected);
}

}  // namespace
}  // namespace dojo::sim
