// Scene sampling for DojoSim: the colour palettes, the background definitions and
// sample_scene() with its object samplers.
#include "sim/scene.h"

#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "core/error.h"
#include "sim/rng.h"
#include "sim/scene_internal.h"

namespace dojo::sim {

// ---------------------------------------------------------------------------------------------
// Palettes

const std::vector<NamedColor>& robot_colors() {
  static const std::vector<NamedColor> colors = {
      {"red", {0.85, 0.15, 0.13, 1}}, {"green", {0.15, 0.68, 0.22, 1}}, {"blue", {0.15, 0.32, 0.85, 1}}};
  return colors;
}

namespace {

const std::vector<NamedColor>& human_only_colors() {
  static const std::vector<NamedColor> colors = {
      {"yellow", {0.95, 0.84, 0.12, 1}}, {"orange", {0.96, 0.5, 0.08, 1}}, {"purple", {0.55, 0.25, 0.75, 1}},
      {"cyan", {0.1, 0.78, 0.85, 1}},    {"white", {0.93, 0.93, 0.9, 1}},  {"pink", {0.96, 0.52, 0.7, 1}},
      {"brown", {0.5, 0.32, 0.17, 1}},   {"black", {0.12, 0.12, 0.13, 1}}};
  return colors;
}

const std::vector<Rgba>& skin_tones() {
  static const std::vector<Rgba> tones = {{0.94, 0.76, 0.64, 1},
                                          {0.87, 0.67, 0.53, 1},
                                          {0.76, 0.56, 0.42, 1},
                                          {0.6, 0.42, 0.3, 1},
                                          {0.42, 0.29, 0.2, 1}};
  return tones;
}

const std::vector<Rgba>& sleeve_colors() {
  static const std::vector<Rgba> colors = {{0.2, 0.3, 0.55, 1}, {0.15, 0.15, 0.17, 1}, {0.55, 0.55, 0.58, 1},
                                           {0.5, 0.15, 0.2, 1}, {0.25, 0.4, 0.3, 1},   {0.85, 0.85, 0.82, 1}};
  return colors;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Backgrounds

const std::vector<BackgroundDef>& backgrounds() {
  static const std::vector<BackgroundDef> defs = {
      // Training backgrounds (0-5).
      {"oak",
       {"flat", {0.62, 0.45, 0.3}, {0.62, 0.45, 0.3}, "random", {0.5, 0.35, 0.22}, 0.05, 4},
       {"flat", {0.42, 0.42, 0.44}, {0.42, 0.42, 0.44}, "none", {0, 0, 0}, 0, 1},
       1.0,
       {1.0, 0.97, 0.92}},
      {"grey-white",
       {"flat", {0.8, 0.8, 0.78}, {0.8, 0.8, 0.78}, "none", {0, 0, 0}, 0, 1},
       {"checker", {0.25, 0.25, 0.27}, {0.35, 0.35, 0.37}, "none", {0, 0, 0}, 0, 8},
       0.9,
       {1.0, 1.0, 1.0}},
      {"checker-beige",
       {"checker", {0.86, 0.8, 0.68}, {0.7, 0.63, 0.52}, "none", {0, 0, 0}, 0, 5},
       {"flat", {0.45, 0.33, 0.24}, {0.45, 0.33, 0.24}, "none", {0, 0, 0}, 0, 1},
       1.0,
       {1.0, 0.98, 0.95}},
      {"green-felt",
       {"flat", {0.2, 0.45, 0.26}, {0.2, 0.45, 0.26}, "random", {0.16, 0.38, 0.21}, 0.08, 6},
       {"flat", {0.5, 0.36, 0.24}, {0.5, 0.36, 0.24}, "random", {0.4, 0.28, 0.18}, 0.05, 4},
       1.05,
       {1.0, 1.0, 0.95}},
      {"blue-gradient",
       {"gradient", {0.38, 0.52, 0.75}, {0.16, 0.22, 0.38}, "none", {0, 0, 0}, 0, 1},
       {"flat", {0.55, 0.55, 0.55}, {0.55, 0.55, 0.55}, "none", {0, 0, 0}, 0, 1},
       1.0,
       {0.95, 0.97, 1.0}},
      {"slate",
       {"flat", {0.27, 0.29, 0.32}, {0.27, 0.29, 0.32}, "random", {0.33, 0.35, 0.38}, 0.03, 3},
       {"checker", {0.75, 0.7, 0.6}, {0.6, 0.55, 0.47}, "none", {0, 0, 0}, 0, 10},
       1.15,
       {1.0, 0.95, 0.88}},
      // Novel backgrounds (6-8), reserved for evaluation.
      {"red-checker",
       {"checker", {0.8, 0.2, 0.2}, {0.95, 0.95, 0.95}, "none", {0, 0, 0}, 0, 8},
       {"flat", {0.12, 0.16, 0.35}, {0.12, 0.16, 0.35}, "none", {0, 0, 0}, 0, 1},
       1.0,
       {1.0, 1.0, 1.0}},
      {"purple-gradient",
       {"gradient", {0.62, 0.34, 0.72}, {0.22, 0.1, 0.3}, "none", {0, 0, 0}, 0, 1},
       {"checker", {0.1, 0.1, 0.1}, {0.2, 0.45, 0.2}, "none", {0, 0, 0}, 0, 10},
       0.95,
       {1.0, 0.92, 1.0}},
      {"yellow-grid",
       {"flat", {0.9, 0.8, 0.35}, {0.9, 0.8, 0.35}, "edge", {0.3, 0.25, 0.1}, 0, 6},
       {"flat", {0.45, 0.18, 0.12}, {0.45, 0.18, 0.12}, "none", {0, 0, 0}, 0, 1},
       0.85,
       {1.0, 0.9, 0.8}},
  };
  return defs;
}

// ---------------------------------------------------------------------------------------------
// Sampling

namespace {

Vec3 scaled(const Vec3& v, double s) { return {v[0] * s, v[1] * s, v[2] * s}; }

ObjectSpec sample_object(Rng& rng, Shape shape, const NamedColor& color, bool graspable) {
  ObjectSpec o;
  o.shape = shape;
  o.color = color.name;
  o.rgba = color.rgba;
  // Horizontal half-extent cap so the robot's gripper (gap 9 cm) can close around it.
  const double cap = graspable ? 0.028 : 1.0;
  auto u = [&](double lo, double hi) { return rng.uniform(lo, std::min(hi, std::max(lo, cap))); };
  double volume = 0.0;
  switch (shape) {
    case Shape::kBox:
      o.size = {u(0.015, 0.045), u(0.015, 0.045), rng.uniform(0.012, 0.04)};
      volume = 8 * o.size[0] * o.size[1] * o.size[2];
      break;
    case Shape::kSphere:
      o.size = {u(0.018, 0.035), 0, 0};
      volume = 4.19 * std::pow(o.size[0], 3);
      break;
    case Shape::kCylinder:
      o.size = {u(0.015, 0.035), rng.uniform(0.015, 0.05), 0};
      volume = M_PI * o.size[0] * o.size[0] * 2 * o.size[1];
      break;
    case Shape::kCapsule:
      o.size = {rng.uniform(0.012, 0.022), rng.uniform(0.02, 0.045), 0};
      volume = M_PI * o.size[0] * o.size[0] * 2 * o.size[1] + 4.19 * std::pow(o.size[0], 3);
      break;
    case Shape::kEllipsoid:
      o.size = {u(0.02, 0.045), u(0.02, 0.045), rng.uniform(0.012, 0.025)};
      volume = 4.19 * o.size[0] * o.size[1] * o.size[2];
      break;
    case Shape::kPlate:
      o.size = {u(0.035, 0.06), rng.uniform(0.004, 0.007), 0};
      volume = M_PI * o.size[0] * o.size[0] * 2 * o.size[1];
      break;
    case Shape::kBottle:
      o.size = {u(0.017, 0.026), rng.uniform(0.04, 0.06), 0};
      volume = M_PI * o.size[0] * o.size[0] * 2 * o.size[1];
      break;
    case Shape::kDumbbell:
      o.size = {rng.uniform(0.013, 0.018), rng.uniform(0.035, 0.05), 0};
      volume = 16 * std::pow(o.size[0], 3);
      break;
    case Shape::kRing:
      o.size = {graspable ? rng.uniform(0.028, 0.034) : rng.uniform(0.03, 0.045), rng.uniform(0.006, 0.009),
                0};
      volume = 2 * M_PI * o.size[0] * M_PI * o.size[1] * o.size[1];
      break;
    case Shape::kMug:
      o.size = {u(0.022, 0.032), rng.uniform(0.025, 0.04), 0};
      volume = M_PI * o.size[0] * o.size[0] * 2 * o.size[1];
      break;
  }
  const double density = rng.uniform(300.0, 1500.0);
  o.mass = std::clamp(density * volume, 0.02, 0.6);
  o.yaw = rng.uniform(-M_PI, M_PI);
  return o;
}

ObjectSpec sample_robot_object(Rng& rng, const NamedColor& color) {
  ObjectSpec o;
  o.color = color.name;
  o.rgba = color.rgba;
  if (rng.bernoulli(0.5)) {
    o.shape = Shape::kBox;
    const double s = rng.uniform(0.02, 0.026);
    o.size = {s, s, s};
  } else {
    o.shape = Shape::kCylinder;
    o.size = {rng.uniform(0.018, 0.024), rng.uniform(0.022, 0.032), 0};
  }
  o.mass = rng.uniform(0.05, 0.15);
  o.yaw = rng.uniform(-M_PI, M_PI);
  return o;
}

}  // namespace

SceneSpec sample_scene(Embodiment embodiment, const SceneSampling& opt, uint64_t seed) {
  const bool robot = embodiment == Embodiment::kRobot;
  const int min_objects = opt.min_objects >= 0 ? opt.min_objects : 1;
  const int max_objects = opt.max_objects >= 0 ? opt.max_objects : (robot ? 3 : 4);
  if (min_objects > max_objects || max_objects > 8) {
    throw UsageError("scene sampling: need 0 <= min_objects <= max_objects <= 8, got " +
                     std::to_string(min_objects) + ".." + std::to_string(max_objects));
  }
  if (opt.width < 16 || opt.height < 16 || opt.width > 4096 || opt.height > 4096) {
    throw UsageError("scene sampling: image size " + std::to_string(opt.width) + "x" +
                     std::to_string(opt.height) + " out of range 16..4096");
  }
  Rng rng(seed * 0x2545F4914F6CDD1DULL + (robot ? 17 : 29));
  SceneSpec spec;
  spec.embodiment = embodiment;
  spec.seed = seed;
  spec.width = opt.width;
  spec.height = opt.height;

  // Background.
  std::vector<int> ids;
  BackgroundSplit split = opt.backgrounds;
  if (split == BackgroundSplit::kDefault) {
    ids = robot ? std::vector<int>{0, 1} : std::vector<int>{0, 1, 2, 3, 4, 5};
  } else if (split == BackgroundSplit::kTrain) {
    for (int i = 0; i < kNumTrainBackgrounds; ++i) ids.push_back(i);
  } else if (split == BackgroundSplit::kNovel) {
    for (int i = kNumTrainBackgrounds; i < kNumBackgrounds; ++i) ids.push_back(i);
  } else {
    for (int i = 0; i < kNumBackgrounds; ++i) ids.push_back(i);
  }
  spec.background = rng.pick(ids);
  const BackgroundDef& bg = backgrounds()[spec.background];

  // Light: the background sets the level and tint; each scene varies direction and strength.
  const double level = bg.light * rng.uniform(0.85, 1.15);
  spec.light.diffuse = scaled(bg.tint, 0.62 * level);
  spec.light.ambient = scaled(bg.tint, 0.28 * level);
  spec.light.headlight = scaled(bg.tint, 0.22 * level);
  spec.light.dir = normalized({rng.uniform(-0.5, 0.5), rng.uniform(-0.2, 0.6), -1.0});
  spec.light.pos = {-spec.light.dir[0] * 1.5, -spec.light.dir[1] * 1.5, 1.5};

  // Camera: the robot's head camera is fixed; a person's head moves a little between clips.
  const double jitter = opt.camera_jitter >= 0 ? opt.camera_jitter : (robot ? 0.0 : 0.03);
  if (jitter > 0) {
    for (int i = 0; i < 3; ++i) spec.camera.pos[i] += rng.uniform(-jitter, jitter);
    for (int i = 0; i < 2; ++i) spec.camera.lookat[i] += rng.uniform(-jitter, jitter) * 0.5;
    spec.camera.fovy += rng.uniform(-3.0, 3.0);
  }

  // Bin.
  const double bin_p = opt.bin_probability >= 0 ? opt.bin_probability : (robot ? 1.0 : 0.3);
  spec.bin.enabled = rng.bernoulli(bin_p);
  if (robot) {
    spec.bin.center = {0.16 + rng.uniform(-0.015, 0.015), 0.14 + rng.uniform(-0.015, 0.015), 0.0};
  } else {
    const double side = rng.bernoulli(0.5) ? 1.0 : -1.0;
    spec.bin.center = {side * rng.uniform(0.15, 0.2), rng.uniform(0.06, 0.12), 0.0};
    const Rgba tray_colors[3] = {{0.35, 0.35, 0.4, 1}, {0.55, 0.45, 0.35, 1}, {0.9, 0.9, 0.88, 1}};
    spec.bin.rgba = tray_colors[rng.randint(0, 2)];
  }

  // Objects.
  ObjectSet set = opt.object_set;
  if (set == ObjectSet::kDefault) set = robot ? ObjectSet::kRobot : ObjectSet::kHuman;
  const int n = rng.randint(min_objects, max_objects);
  std::vector<NamedColor> all_colors = robot_colors();
  for (const auto& c : human_only_colors()) all_colors.push_back(c);
  for (int i = 0; i < n; ++i) {
    ObjectSpec o;
    if (set == ObjectSet::kRobot) {
      o = sample_robot_object(rng, rng.pick(robot_colors()));
    } else if (set == ObjectSet::kHuman) {
      const Shape shape = static_cast<Shape>(rng.randint(0, kNumShapes - 1));
      o = sample_object(rng, shape, rng.pick(all_colors), robot);
    } else {
      static const std::vector<Shape> shapes = {Shape::kSphere, Shape::kCapsule,  Shape::kEllipsoid,
                                                Shape::kBottle, Shape::kDumbbell, Shape::kRing,
                                                Shape::kMug,    Shape::kBox};
      o = sample_object(rng, rng.pick(shapes), rng.pick(human_only_colors()), true);
    }
    spec.objects.push_back(o);
  }

  // Placement by rejection: no overlaps, clear of the bin and of the embodiment's start pose.
  const double x_lo = robot ? -0.17 : -0.2, x_hi = robot ? 0.08 : 0.2;
  const double y_lo = robot ? -0.12 : -0.1, y_hi = robot ? 0.12 : 0.17;
  std::vector<ObjectSpec> placed;
  for (ObjectSpec o : spec.objects) {
    const double r = object_footprint_radius(o);
    bool ok = false;
    for (int attempt = 0; attempt < 300 && !ok; ++attempt) {
      o.pos = {rng.uniform(x_lo + r, x_hi - r), rng.uniform(y_lo + r, y_hi - r), 0.0};
      ok = true;
      for (const auto& p : placed) {
        if (std::hypot(o.pos[0] - p.pos[0], o.pos[1] - p.pos[1]) < r + object_footprint_radius(p) + 0.02)
          ok = false;
      }
      if (spec.bin.enabled) {
        const auto& b = spec.bin;
        if (std::fabs(o.pos[0] - b.center[0]) < b.half_x + 2 * b.wall_thickness + r + 0.015 &&
            std::fabs(o.pos[1] - b.center[1]) < b.half_y + 2 * b.wall_thickness + r + 0.015) {
          ok = false;
        }
      }
    }
    if (ok) placed.push_back(o);  // an object that does not fit is dropped
  }
  spec.objects = placed;

  if (!robot) {
    spec.skin = rng.pick(skin_tones());
    spec.sleeve = rng.pick(sleeve_colors());
    spec.initial_command = {rng.uniform(0.06, 0.16),
                            rng.uniform(-0.24, -0.17),
                            rng.uniform(0.12, 0.17),
                            rng.uniform(0.05, 0.45),
                            0.0,
                            0.25};
  }
  return spec;
}

}  // namespace dojo::sim
