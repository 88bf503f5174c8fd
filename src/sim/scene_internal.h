// Internal to src/sim: what scene.cpp, scene_mjcf.cpp and scene_sampling.cpp share: the colour
// palette of the robot's object set and the background definitions (both defined in
// scene_sampling.cpp), and a vector helper (defined in scene.cpp).
#pragma once

#include <vector>

#include "sim/scene.h"

namespace dojo::sim {

// ---------------------------------------------------------------------------------------------
// Palettes

struct NamedColor {
  const char* name;
  Rgba rgba;
};

const std::vector<NamedColor>& robot_colors();

// ---------------------------------------------------------------------------------------------
// Backgrounds: table and floor textures from MuJoCo's builtin generators, plus a light level.

struct TextureDef {
  const char* builtin;  // "flat", "checker", "gradient"
  Vec3 rgb1, rgb2;
  const char* mark;  // "none", "edge", "cross", "random"
  Vec3 markrgb;
  double random;  // fraction of random marks
  double repeat;  // texrepeat
};

struct BackgroundDef {
  const char* name;
  TextureDef table;
  TextureDef floor;
  double light;  // diffuse scale
  Vec3 tint;     // light colour tint
};

// kNumBackgrounds definitions, indexed by SceneSpec::background.
const std::vector<BackgroundDef>& backgrounds();

Vec3 normalized(const Vec3& v);

}  // namespace dojo::sim
