#include "sim/scene.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>

#include <nlohmann/json.hpp>

#include "core/error.h"
#include "sim/rng.h"
#include "sim/robot_arm.h"

namespace dojo::sim {
namespace {

// ---------------------------------------------------------------------------------------------
// Palettes

struct NamedColor {
  const char* name;
  Rgba rgba;
};

const std::vector<NamedColor>& robot_colors() {
  static const std::vector<NamedColor> colors = {
      {"red", {0.85, 0.15, 0.13, 1}}, {"green", {0.15, 0.68, 0.22, 1}}, {"blue", {0.15, 0.32, 0.85, 1}}};
  return colors;
}

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
// Formatting helpers for the MJCF text.

std::string num(double v) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%.6g", std::fabs(v) < 1e-12 ? 0.0 : v);
  return buf;
}
std::string vec(const Vec3& v) { return num(v[0]) + " " + num(v[1]) + " " + num(v[2]); }
std::string rgba(const Rgba& c) { return num(c[0]) + " " + num(c[1]) + " " + num(c[2]) + " " + num(c[3]); }
std::string fromto(double ax, double ay, double az, double bx, double by, double bz) {
  return num(ax) + " " + num(ay) + " " + num(az) + " " + num(bx) + " " + num(by) + " " + num(bz);
}
Vec3 scaled(const Vec3& v, double s) { return {v[0] * s, v[1] * s, v[2] * s}; }

Vec3 normalized(const Vec3& v) {
  const double n = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  return {v[0] / n, v[1] / n, v[2] / n};
}
Vec3 cross(const Vec3& a, const Vec3& b) {
  return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}

void write_texture(std::ostringstream& x, const std::string& name, const TextureDef& t) {
  x << "    <texture name=\"" << name << "\" type=\"2d\" builtin=\"" << t.builtin << "\" rgb1=\""
    << vec(t.rgb1) << "\" rgb2=\"" << vec(t.rgb2) << "\" width=\"256\" height=\"256\"";
  if (std::string(t.mark) != "none") {
    x << " mark=\"" << t.mark << "\" markrgb=\"" << vec(t.markrgb) << "\"";
    if (t.random > 0) x << " random=\"" << num(t.random) << "\"";
  }
  x << "/>\n";
}

// Collision classes: the static world and objects collide with everything; embodiment geoms
// (contype 2, conaffinity 1) collide with the world and objects but not with each other.
constexpr const char* kWorldCollide = "contype=\"1\" conaffinity=\"3\"";
constexpr const char* kBodyCollide = "contype=\"2\" conaffinity=\"1\"";
constexpr const char* kNoCollide = "contype=\"0\" conaffinity=\"0\"";

// Round shapes get rolling friction (condim 6) so a pushed ball slows down instead of rolling
// forever; flat-bottomed shapes use condim 4 (torsional friction) for stable grasps.
bool is_round(Shape s) {
  return s == Shape::kSphere || s == Shape::kCapsule || s == Shape::kEllipsoid || s == Shape::kCylinder ||
         s == Shape::kBottle || s == Shape::kMug;
}

void write_object(std::ostringstream& x, const ObjectSpec& o, int index) {
  const double hh = object_half_height(o);
  const double z = hh + 0.001;
  const double c = std::cos(o.yaw / 2), s = std::sin(o.yaw / 2);
  x << "    <body name=\"obj" << index << "\" pos=\"" << num(o.pos[0]) << " " << num(o.pos[1]) << " "
    << num(z) << "\" quat=\"" << num(c) << " 0 0 " << num(s) << "\">\n";
  x << "      <freejoint name=\"obj" << index << "_joint\"/>\n";
  const std::string common = std::string(kWorldCollide) + " rgba=\"" + rgba(o.rgba) + "\" condim=\"" +
                             (is_round(o.shape) ? "6" : "4") + "\" friction=\"0.9 0.01 " +
                             (is_round(o.shape) ? "0.002" : "0.0001") + "\"";
  auto geom = [&](const std::string& body, double mass) {
    x << "      <geom " << body << " mass=\"" << num(mass) << "\" " << common << "/>\n";
  };
  // MuJoCo 2.2 collides cylinders with boxes through its general convex routine, which yields a
  // single contact point: a cylinder resting on a box (the table, the bin, a stacked block)
  // rocks forever. Small hidden spheres on both rims give it a proper multi-point support.
  auto rim_spheres = [&](double r, double h, double z0) {
    const double rho = 0.0015;
    for (int k = 0; k < 8; ++k) {
      const double a = 2 * M_PI * k / 8;
      for (double zs : {-1.0, 1.0}) {
        x << "      <geom type=\"sphere\" size=\"" << num(rho) << "\" pos=\"" << num((r - rho) * std::cos(a))
          << " " << num((r - rho) * std::sin(a)) << " " << num(z0 + zs * (h - rho))
          << "\" mass=\"0\" group=\"3\" " << common << "/>\n";
      }
    }
  };
  const double m = o.mass;
  const Vec3& sz = o.size;
  switch (o.shape) {
    case Shape::kBox:
      geom("type=\"box\" size=\"" + vec(sz) + "\"", m);
      break;
    case Shape::kSphere:
      geom("type=\"sphere\" size=\"" + num(sz[0]) + "\"", m);
      break;
    case Shape::kCylinder:
    case Shape::kPlate:
      geom("type=\"cylinder\" size=\"" + num(sz[0]) + " " + num(sz[1]) + "\"", m);
      rim_spheres(sz[0], sz[1], 0.0);
      break;
    case Shape::kCapsule:
      geom(
          "type=\"capsule\" fromto=\"" + fromto(-sz[1], 0, 0, sz[1], 0, 0) + "\" size=\"" + num(sz[0]) + "\"",
          m);
      break;
    case Shape::kEllipsoid:
      geom("type=\"ellipsoid\" size=\"" + vec(sz) + "\"", m);
      break;
    case Shape::kBottle: {
      const double r = sz[0], h = sz[1];
      geom("type=\"cylinder\" size=\"" + num(r) + " " + num(h) + "\"", 0.85 * m);
      rim_spheres(r, h, 0.0);
      geom("type=\"cylinder\" pos=\"0 0 " + num(h + 0.25 * h) + "\" size=\"" + num(0.45 * r) + " " +
               num(0.25 * h) + "\"",
           0.1 * m);
      x << "      <geom type=\"cylinder\" pos=\"0 0 " << num(h + 0.5 * h + 0.006) << "\" size=\""
        << num(0.5 * r) << " 0.006\" mass=\"" << num(0.05 * m) << "\" " << kWorldCollide
        << " rgba=\"0.95 0.95 0.95 1\"/>\n";
      break;
    }
    case Shape::kDumbbell: {
      const double cube = sz[0], d = sz[1];
      geom("type=\"box\" pos=\"" + num(-d) + " 0 0\" size=\"" + num(cube) + " " + num(cube) + " " +
               num(cube) + "\"",
           0.42 * m);
      geom("type=\"box\" pos=\"" + num(d) + " 0 0\" size=\"" + num(cube) + " " + num(cube) + " " + num(cube) +
               "\"",
           0.42 * m);
      geom("type=\"capsule\" fromto=\"" + fromto(-d, 0, 0, d, 0, 0) + "\" size=\"" + num(0.4 * cube) + "\"",
           0.16 * m);
      break;
    }
    case Shape::kRing: {
      const int n = 10;
      const double R = sz[0], t = sz[1];
      for (int k = 0; k < n; ++k) {
        const double a0 = 2 * M_PI * k / n, a1 = 2 * M_PI * (k + 1) / n;
        geom("type=\"capsule\" fromto=\"" +
                 fromto(R * std::cos(a0), R * std::sin(a0), 0, R * std::cos(a1), R * std::sin(a1), 0) +
                 "\" size=\"" + num(t) + "\"",
             m / n);
      }
      break;
    }
    case Shape::kMug: {
      const double r = sz[0], h = sz[1], hz = 0.55 * h, hx = 1.5 * r, t = 0.16 * r;
      geom("type=\"cylinder\" size=\"" + num(r) + " " + num(h) + "\"", 0.85 * m);
      rim_spheres(r, h, 0.0);
      geom("type=\"capsule\" fromto=\"" + fromto(0.9 * r, 0, hz, hx, 0, hz) + "\" size=\"" + num(t) + "\"",
           0.05 * m);
      geom("type=\"capsule\" fromto=\"" + fromto(hx, 0, hz, hx, 0, -hz) + "\" size=\"" + num(t) + "\"",
           0.05 * m);
      geom("type=\"capsule\" fromto=\"" + fromto(hx, 0, -hz, 0.9 * r, 0, -hz) + "\" size=\"" + num(t) + "\"",
           0.05 * m);
      // The dark disc on top reads as the mug's opening; it is visual only.
      x << "      <geom type=\"cylinder\" pos=\"0 0 " << num(h) << "\" size=\"" << num(0.82 * r)
        << " 0.0008\" " << kNoCollide << " mass=\"0\" rgba=\"0.15 0.1 0.08 1\"/>\n";
      break;
    }
  }
  x << "    </body>\n";
}

void write_robot(std::ostringstream& x) {
  using namespace arm;
  const char* light = "rgba=\"0.86 0.87 0.9 1\"";
  const char* dark = "rgba=\"0.2 0.21 0.24 1\"";
  const auto& L = kJointLimits;
  auto range = [&](int j) { return "range=\"" + num(L[j].lo) + " " + num(L[j].hi) + "\""; };
  const double column = kShoulderZ - kYawHeight;
  x << "    <body name=\"arm_base\" pos=\"" << num(kBaseX) << " " << num(kBaseY) << " 0\">\n"
    << "      <geom type=\"cylinder\" size=\"0.065 " << num(kYawHeight / 2) << "\" pos=\"0 0 "
    << num(kYawHeight / 2) << "\" " << dark << " " << kBodyCollide << "/>\n"
    << "      <body name=\"arm_link0\" pos=\"0 0 " << num(kYawHeight) << "\">\n"
    << "        <joint name=\"base_yaw\" axis=\"0 0 1\" limited=\"true\" " << range(0)
    << " damping=\"8\" armature=\"0.02\"/>\n"
    << "        <geom type=\"cylinder\" size=\"0.042 " << num(column / 2) << "\" pos=\"0 0 "
    << num(column / 2) << "\" " << light << " " << kBodyCollide << "/>\n"
    << "        <body name=\"arm_upper\" pos=\"0 0 " << num(column) << "\">\n"
    << "          <joint name=\"shoulder\" axis=\"-1 0 0\" limited=\"true\" " << range(1)
    << " damping=\"15\" armature=\"0.02\"/>\n"
    << "          <geom type=\"cylinder\" fromto=\"-0.04 0 0 0.04 0 0\" size=\"0.036\" " << dark << " "
    << kBodyCollide << "/>\n"
    << "          <geom type=\"capsule\" fromto=\"0 0 0 0 0 " << num(kUpperLen) << "\" size=\"0.026\" "
    << light << " " << kBodyCollide << "/>\n"
    << "          <body name=\"arm_fore\" pos=\"0 0 " << num(kUpperLen) << "\">\n"
    << "            <joint name=\"elbow\" axis=\"-1 0 0\" limited=\"true\" " << range(2)
    << " damping=\"10\" armature=\"0.02\"/>\n"
    << "            <geom type=\"cylinder\" fromto=\"-0.034 0 0 0.034 0 0\" size=\"0.03\" " << dark << " "
    << kBodyCollide << "/>\n"
    << "            <geom type=\"capsule\" fromto=\"0 0 0 0 0 " << num(kForeLen) << "\" size=\"0.021\" "
    << light << " " << kBodyCollide << "/>\n"
    << "            <body name=\"arm_wrist\" pos=\"0 0 " << num(kForeLen) << "\">\n"
    << "              <joint name=\"wrist_pitch\" axis=\"-1 0 0\" limited=\"true\" " << range(3)
    << " damping=\"3\" armature=\"0.005\"/>\n"
    << "              <geom type=\"cylinder\" fromto=\"-0.028 0 0 0.028 0 0\" size=\"0.024\" " << dark << " "
    << kBodyCollide << "/>\n"
    << "              <body name=\"arm_hand\">\n"
    << "                <joint name=\"wrist_roll\" axis=\"0 0 1\" limited=\"true\" " << range(4)
    << " damping=\"1\" armature=\"0.005\"/>\n"
    << "                <geom type=\"cylinder\" fromto=\"0 0 0 0 0 0.045\" size=\"0.019\" " << light << " "
    << kBodyCollide << "/>\n"
    << "                <geom type=\"box\" pos=\"0 0 0.0525\" size=\"0.064 0.021 0.0075\" " << dark << " "
    << kBodyCollide << "/>\n";
  for (int side = 0; side < 2; ++side) {
    const char* name = side == 0 ? "finger_l" : "finger_r";
    const double sign = side == 0 ? -1.0 : 1.0;
    x << "                <body name=\"" << name << "\" pos=\"0 0 " << num(kFingerStart) << "\">\n"
      << "                  <joint name=\"" << name << "\" type=\"slide\" axis=\"" << num(sign)
      << " 0 0\" limited=\"true\" range=\"0 " << num(kFingerTravel)
      << "\" damping=\"5\" armature=\"0.01\"/>\n"
      << "                  <geom type=\"box\" pos=\"" << num(sign * 0.006) << " 0 " << num(kFingerLen / 2)
      << "\" size=\"0.006 0.012 " << num(kFingerLen / 2) << "\" rgba=\"0.3 0.31 0.34 1\" " << kBodyCollide
      << " condim=\"4\" friction=\"1.5 0.02 0.0001\" mass=\"0.03\"/>\n"
      << "                </body>\n";
  }
  x << "                <site name=\"grasp\" pos=\"0 0 " << num(kGripLen)
    << "\" size=\"0.004\" rgba=\"1 1 1 0\"/>\n"
    << "              </body>\n"
    << "            </body>\n"
    << "          </body>\n"
    << "        </body>\n"
    << "      </body>\n"
    << "    </body>\n";
}

// The human hand is a right hand, palm down, fingers along +y at yaw 0. Its root slides in
// x, y, z and turns in yaw and pitch; each finger has two hinges and the thumb two more.
struct FingerDef {
  double x, len1, len2, radius;
};
const FingerDef kFingers[4] = {{-0.029, 0.042, 0.032, 0.0088},
                               {-0.0095, 0.046, 0.035, 0.009},
                               {0.0095, 0.043, 0.033, 0.0088},
                               {0.029, 0.034, 0.026, 0.0078}};

void write_hand(std::ostringstream& x, const SceneSpec& spec) {
  const std::string skin = "rgba=\"" + rgba(spec.skin) + "\"";
  const std::string sleeve = "rgba=\"" + rgba(spec.sleeve) + "\"";
  x << "    <body name=\"hand\" pos=\"0 0 0\">\n"
    << "      <joint name=\"hand_x\" type=\"slide\" axis=\"1 0 0\" limited=\"true\" range=\"-0.45 0.45\" "
       "damping=\"40\"/>\n"
    << "      <joint name=\"hand_y\" type=\"slide\" axis=\"0 1 0\" limited=\"true\" range=\"-0.5 0.4\" "
       "damping=\"40\"/>\n"
    << "      <joint name=\"hand_z\" type=\"slide\" axis=\"0 0 1\" limited=\"true\" range=\"0 0.5\" "
       "damping=\"40\"/>\n"
    << "      <joint name=\"hand_yaw\" axis=\"0 0 1\" limited=\"true\" range=\"-2.6 2.6\" damping=\"1.5\" "
       "armature=\"0.005\"/>\n"
    << "      <joint name=\"hand_pitch\" axis=\"-1 0 0\" limited=\"true\" range=\"-0.6 1.3\" damping=\"1.5\" "
       "armature=\"0.005\"/>\n"
    << "      <geom name=\"palm\" type=\"box\" size=\"0.039 0.044 0.011\" mass=\"0.35\" " << skin << " "
    << kBodyCollide << " friction=\"1.2 0.02 0.0001\"/>\n"
    << "      <geom type=\"capsule\" fromto=\"-0.038 0.044 0 0.038 0.044 0\" size=\"0.011\" mass=\"0.02\" "
    << skin << " " << kBodyCollide << "/>\n"
    << "      <geom type=\"capsule\" fromto=\"0.039 -0.04 0 0.039 0.04 0\" size=\"0.0105\" mass=\"0.02\" "
    << skin << " " << kBodyCollide
    << "/>\n"
    // The wrist stub is visual only; the forearm and upper arm are separate mocap bodies that
    // World poses each step to connect the wrist to a shoulder beside the camera.
    << "      <geom type=\"capsule\" fromto=\"0 -0.036 0.003 0.002 -0.07 0.008\" size=\"0.026\" "
       "mass=\"0.01\" "
    << skin << " " << kNoCollide << "/>\n";
  for (int i = 0; i < 4; ++i) {
    const FingerDef& f = kFingers[i];
    x << "      <body name=\"f" << i << "_prox\" pos=\"" << num(f.x) << " 0.046 0\">\n"
      << "        <joint name=\"f" << i
      << "_j1\" axis=\"-1 0 0\" limited=\"true\" range=\"-0.15 1.6\" damping=\"0.02\" "
         "armature=\"0.0005\"/>\n"
      << "        <geom type=\"capsule\" fromto=\"0 0 0 0 " << num(f.len1) << " 0\" size=\"" << num(f.radius)
      << "\" mass=\"0.012\" " << skin << " " << kBodyCollide << " friction=\"1.2 0.02 0.0001\"/>\n"
      << "        <body name=\"f" << i << "_dist\" pos=\"0 " << num(f.len1) << " 0\">\n"
      << "          <joint name=\"f" << i
      << "_j2\" axis=\"-1 0 0\" limited=\"true\" range=\"-0.1 1.8\" damping=\"0.02\" "
         "armature=\"0.0005\"/>\n"
      << "          <geom type=\"capsule\" fromto=\"0 0 0 0 " << num(f.len2) << " -0.002\" size=\""
      << num(0.92 * f.radius) << "\" mass=\"0.008\" " << skin << " " << kBodyCollide
      << " friction=\"1.2 0.02 0.0001\"/>\n"
      << "        </body>\n"
      << "      </body>\n";
  }
  x << "      <body name=\"thumb_prox\" pos=\"-0.036 -0.016 -0.003\">\n"
    << "        <joint name=\"thumb_j1\" axis=\"0.2 -1 0\" limited=\"true\" range=\"-0.2 1.4\" "
       "damping=\"0.02\" "
       "armature=\"0.0005\"/>\n"
    << "        <geom type=\"capsule\" fromto=\"0 0 0 -0.024 0.03 -0.006\" size=\"0.0105\" mass=\"0.012\" "
    << skin << " " << kBodyCollide << " friction=\"1.2 0.02 0.0001\"/>\n"
    << "        <body name=\"thumb_dist\" pos=\"-0.024 0.03 -0.006\">\n"
    << "          <joint name=\"thumb_j2\" axis=\"0.2 -1 0\" limited=\"true\" range=\"-0.2 1.4\" "
       "damping=\"0.02\" "
       "armature=\"0.0005\"/>\n"
    << "          <geom type=\"capsule\" fromto=\"0 0 0 -0.006 0.028 -0.004\" size=\"0.0095\" mass=\"0.008\" "
    << skin << " " << kBodyCollide << " friction=\"1.2 0.02 0.0001\"/>\n"
    << "        </body>\n"
    << "      </body>\n"
    << "    </body>\n"
    << "    <body name=\"forearm_vis\" mocap=\"true\">\n"
    << "      <geom type=\"capsule\" fromto=\"0 0 0 0 0 " << num(kHumanForearmLen) << "\" size=\"0.03\" "
    << skin << " " << kNoCollide << "/>\n"
    << "    </body>\n"
    << "    <body name=\"upper_arm_vis\" mocap=\"true\">\n"
    << "      <geom type=\"capsule\" fromto=\"0 0 0 0 0 " << num(kHumanUpperArmLen) << "\" size=\"0.042\" "
    << sleeve << " " << kNoCollide << "/>\n"
    << "    </body>\n";
}

void write_bin(std::ostringstream& x, const BinSpec& b) {
  const double t = b.wall_thickness, h = b.wall_height;
  const std::string col = std::string(kWorldCollide) + " rgba=\"" + rgba(b.rgba) + "\"";
  const Vec3& c = b.center;
  x << "    <geom name=\"bin_floor\" type=\"box\" pos=\"" << num(c[0]) << " " << num(c[1])
    << " 0.002\" size=\"" << num(b.half_x + 2 * t) << " " << num(b.half_y + 2 * t) << " 0.002\" " << col
    << "/>\n";
  x << "    <geom name=\"bin_wall_xn\" type=\"box\" pos=\"" << num(c[0] - b.half_x - t) << " " << num(c[1])
    << " " << num(h / 2) << "\" size=\"" << num(t) << " " << num(b.half_y + 2 * t) << " " << num(h / 2)
    << "\" " << col << "/>\n";
  x << "    <geom name=\"bin_wall_xp\" type=\"box\" pos=\"" << num(c[0] + b.half_x + t) << " " << num(c[1])
    << " " << num(h / 2) << "\" size=\"" << num(t) << " " << num(b.half_y + 2 * t) << " " << num(h / 2)
    << "\" " << col << "/>\n";
  x << "    <geom name=\"bin_wall_yn\" type=\"box\" pos=\"" << num(c[0]) << " " << num(c[1] - b.half_y - t)
    << " " << num(h / 2) << "\" size=\"" << num(b.half_x) << " " << num(t) << " " << num(h / 2) << "\" "
    << col << "/>\n";
  x << "    <geom name=\"bin_wall_yp\" type=\"box\" pos=\"" << num(c[0]) << " " << num(c[1] + b.half_y + t)
    << " " << num(h / 2) << "\" size=\"" << num(b.half_x) << " " << num(t) << " " << num(h / 2) << "\" "
    << col << "/>\n";
}

// ---------------------------------------------------------------------------------------------
// Sampling

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

// -----------------------------------------------------------------------------------------------

const char* to_string(Embodiment e) { return e == Embodiment::kHuman ? "human" : "robot"; }

const char* to_string(Shape s) {
  switch (s) {
    case Shape::kBox:
      return "box";
    case Shape::kSphere:
      return "sphere";
    case Shape::kCylinder:
      return "cylinder";
    case Shape::kCapsule:
      return "capsule";
    case Shape::kEllipsoid:
      return "ellipsoid";
    case Shape::kPlate:
      return "plate";
    case Shape::kBottle:
      return "bottle";
    case Shape::kDumbbell:
      return "dumbbell";
    case Shape::kRing:
      return "ring";
    case Shape::kMug:
      return "mug";
  }
  return "?";
}

Embodiment parse_embodiment(const std::string& name) {
  if (name == "human") return Embodiment::kHuman;
  if (name == "robot") return Embodiment::kRobot;
  throw UsageError("unknown embodiment '" + name + "' (expected human or robot)");
}

Shape parse_shape(const std::string& name) {
  for (int i = 0; i < kNumShapes; ++i) {
    if (name == to_string(static_cast<Shape>(i))) return static_cast<Shape>(i);
  }
  throw UsageError("unknown object shape '" + name + "'");
}

double object_half_height(const ObjectSpec& o) {
  switch (o.shape) {
    case Shape::kBox:
    case Shape::kEllipsoid:
      return o.size[2];
    case Shape::kSphere:
    case Shape::kCapsule:
      return o.size[0];
    case Shape::kCylinder:
    case Shape::kPlate:
    case Shape::kBottle:
    case Shape::kMug:
      return o.size[1];
    case Shape::kDumbbell:
      return o.size[0];
    case Shape::kRing:
      return o.size[1];
  }
  return 0.0;
}

double object_footprint_radius(const ObjectSpec& o) {
  switch (o.shape) {
    case Shape::kBox:
      return std::hypot(o.size[0], o.size[1]);
    case Shape::kEllipsoid:
      return std::max(o.size[0], o.size[1]);
    case Shape::kSphere:
    case Shape::kCylinder:
    case Shape::kPlate:
    case Shape::kBottle:
      return o.size[0];
    case Shape::kCapsule:
      return o.size[0] + o.size[1];
    case Shape::kDumbbell:
      return o.size[1] + o.size[0] * 1.42;
    case Shape::kRing:
      return o.size[0] + o.size[1];
    case Shape::kMug:
      return 1.5 * o.size[0] + 0.16 * o.size[0];
  }
  return 0.05;
}

bool in_robot_set(const ObjectSpec& o) {
  bool color_ok = false;
  for (const auto& c : robot_colors()) color_ok |= (o.color == c.name);
  const bool cube = o.shape == Shape::kBox && std::fabs(o.size[0] - o.size[1]) < 1e-9 &&
                    std::fabs(o.size[0] - o.size[2]) < 1e-9;
  return color_ok && (cube || o.shape == Shape::kCylinder);
}

std::string object_description(const ObjectSpec& o) {
  std::string noun = to_string(o.shape);
  if (o.shape == Shape::kBox) {
    const bool cube = std::fabs(o.size[0] - o.size[1]) < 1e-9 && std::fabs(o.size[0] - o.size[2]) < 1e-9;
    noun = cube ? "cube" : (o.size[2] > 1.4 * std::max(o.size[0], o.size[1]) ? "block" : "box");
  } else if (o.shape == Shape::kSphere) {
    noun = "ball";
  } else if (o.shape == Shape::kEllipsoid) {
    noun = "egg";
  }
  return o.color + " " + noun;
}

std::string background_name(int background) {
  DOJO_CHECK(background >= 0 && background < kNumBackgrounds, "background id " + std::to_string(background) +
                                                                  " out of range 0.." +
                                                                  std::to_string(kNumBackgrounds - 1));
  return backgrounds()[background].name;
}

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

std::string build_mjcf(const SceneSpec& spec) {
  DOJO_CHECK(spec.background >= 0 && spec.background < kNumBackgrounds,
             "scene: background id " + std::to_string(spec.background) + " out of range");
  DOJO_CHECK(spec.width >= 1 && spec.height >= 1, "scene: image size must be positive");
  DOJO_CHECK(spec.timestep > 0 && spec.substeps >= 1, "scene: timestep and substeps must be positive");
  const BackgroundDef& bg = backgrounds()[spec.background];
  std::ostringstream x;
  x << "<mujoco model=\"dojosim\">\n"
    << "  <compiler angle=\"radian\"/>\n"
    << "  <option timestep=\"" << num(spec.timestep)
    << "\" cone=\"elliptic\" impratio=\"10\" iterations=\"50\" tolerance=\"1e-8\"/>\n"
    << "  <size njmax=\"1000\" nconmax=\"200\"/>\n"
    << "  <visual>\n"
    << "    <global offwidth=\"" << spec.width << "\" offheight=\"" << spec.height << "\"/>\n"
    << "    <quality offsamples=\"" << spec.msaa_samples << "\" shadowsize=\"0\"/>\n"
    << "    <headlight ambient=\"" << vec(spec.light.ambient) << "\" diffuse=\"" << vec(spec.light.headlight)
    << "\" specular=\"0 0 0\"/>\n"
    << "    <map znear=\"0.005\" zfar=\"20\"/>\n"
    << "  </visual>\n"
    << "  <asset>\n";
  write_texture(x, "table_tex", bg.table);
  write_texture(x, "floor_tex", bg.floor);
  x << "    <texture name=\"sky\" type=\"skybox\" builtin=\"gradient\" rgb1=\"0.75 0.75 0.72\" rgb2=\"0.45 "
       "0.45 0.43\" "
       "width=\"32\" height=\"32\"/>\n"
    << "    <material name=\"table_mat\" texture=\"table_tex\" texrepeat=\"" << num(bg.table.repeat) << " "
    << num(bg.table.repeat) << "\" specular=\"0.15\" shininess=\"0.2\"/>\n"
    << "    <material name=\"floor_mat\" texture=\"floor_tex\" texrepeat=\"" << num(bg.floor.repeat) << " "
    << num(bg.floor.repeat) << "\" specular=\"0.05\"/>\n"
    << "  </asset>\n"
    << "  <worldbody>\n"
    << "    <light name=\"sun\" directional=\"true\" pos=\"" << vec(spec.light.pos) << "\" dir=\""
    << vec(spec.light.dir) << "\" diffuse=\"" << vec(spec.light.diffuse)
    << "\" specular=\"0.15 0.15 0.15\" castshadow=\"false\"/>\n"
    << "    <geom name=\"floor\" type=\"plane\" pos=\"0 0 -0.75\" size=\"6 6 0.05\" material=\"floor_mat\" "
    << kWorldCollide << "/>\n"
    << "    <geom name=\"table\" type=\"box\" pos=\"0 0 -0.025\" size=\"0.55 0.42 0.025\" "
       "material=\"table_mat\" "
    << kWorldCollide << " friction=\"0.8 0.01 0.0001\"/>\n";
  for (double lx : {-0.5, 0.5}) {
    for (double ly : {-0.37, 0.37}) {
      x << "    <geom type=\"box\" pos=\"" << num(lx) << " " << num(ly)
        << " -0.4\" size=\"0.025 0.025 0.35\" " << kNoCollide << " rgba=\"0.3 0.25 0.2 1\"/>\n";
    }
  }
  if (spec.bin.enabled) write_bin(x, spec.bin);
  for (size_t i = 0; i < spec.objects.size(); ++i) write_object(x, spec.objects[i], static_cast<int>(i));
  if (spec.embodiment == Embodiment::kRobot) {
    write_robot(x);
  } else {
    write_hand(x, spec);
  }
  // Egocentric camera: MuJoCo cameras look along their -z axis; x is image-right, y image-up.
  const Vec3& p = spec.camera.pos;
  const Vec3 f =
      normalized({spec.camera.lookat[0] - p[0], spec.camera.lookat[1] - p[1], spec.camera.lookat[2] - p[2]});
  const Vec3 right = normalized(cross(f, {0, 0, 1}));
  const Vec3 up = cross(right, f);
  x << "    <camera name=\"ego\" pos=\"" << vec(p) << "\" xyaxes=\"" << vec(right) << " " << vec(up)
    << "\" fovy=\"" << num(spec.camera.fovy) << "\"/>\n"
    << "  </worldbody>\n";

  if (spec.embodiment == Embodiment::kHuman && !spec.objects.empty()) {
    // Grasp assist welds (inactive until World switches one on; see world.h).
    x << "  <equality>\n";
    for (size_t i = 0; i < spec.objects.size(); ++i) {
      x << "    <weld name=\"grasp" << i << "\" body1=\"hand\" body2=\"obj" << i
        << "\" active=\"false\" solref=\"0.02 1\"/>\n";
    }
    x << "  </equality>\n";
  }

  x << "  <actuator>\n";
  auto position = [&](const std::string& joint, double kp, double lo, double hi) {
    x << "    <position name=\"act_" << joint << "\" joint=\"" << joint << "\" kp=\"" << num(kp)
      << "\" ctrllimited=\"true\" ctrlrange=\"" << num(lo) << " " << num(hi) << "\"/>\n";
  };
  if (spec.embodiment == Embodiment::kRobot) {
    const char* names[5] = {"base_yaw", "shoulder", "elbow", "wrist_pitch", "wrist_roll"};
    const double kp[5] = {150, 300, 200, 60, 20};
    for (int j = 0; j < 5; ++j) position(names[j], kp[j], arm::kJointLimits[j].lo, arm::kJointLimits[j].hi);
    position("finger_l", 200, 0, arm::kFingerTravel);
    position("finger_r", 200, 0, arm::kFingerTravel);
  } else {
    position("hand_x", 800, -0.45, 0.45);
    position("hand_y", 800, -0.5, 0.4);
    position("hand_z", 800, 0, 0.5);
    position("hand_yaw", 30, -2.6, 2.6);
    position("hand_pitch", 30, -0.6, 1.3);
    for (int i = 0; i < 4; ++i) {
      position("f" + std::to_string(i) + "_j1", 0.6, -0.15, 1.6);
      position("f" + std::to_string(i) + "_j2", 0.4, -0.1, 1.8);
    }
    position("thumb_j1", 0.6, -0.2, 1.4);
    position("thumb_j2", 0.4, -0.2, 1.4);
  }
  x << "  </actuator>\n"
    << "</mujoco>\n";
  return x.str();
}

// -----------------------------------------------------------------------------------------------
// JSON

nlohmann::json to_json(const ObjectSpec& o) {
  return {{"shape", to_string(o.shape)},
          {"size", o.size},
          {"rgba", o.rgba},
          {"color", o.color},
          {"mass", o.mass},
          {"pos", o.pos},
          {"yaw", o.yaw},
          {"description", object_description(o)}};
}

nlohmann::json to_json(const SceneSpec& s) {
  nlohmann::json objects = nlohmann::json::array();
  for (const auto& o : s.objects) objects.push_back(to_json(o));
  return {{"embodiment", to_string(s.embodiment)},
          {"objects", objects},
          {"background", s.background},
          {"background_name", background_name(s.background)},
          {"light",
           {{"pos", s.light.pos},
            {"dir", s.light.dir},
            {"diffuse", s.light.diffuse},
            {"ambient", s.light.ambient},
            {"headlight", s.light.headlight}}},
          {"camera", {{"pos", s.camera.pos}, {"lookat", s.camera.lookat}, {"fovy", s.camera.fovy}}},
          {"bin",
           {{"enabled", s.bin.enabled},
            {"center", s.bin.center},
            {"half_x", s.bin.half_x},
            {"half_y", s.bin.half_y},
            {"wall_height", s.bin.wall_height},
            {"wall_thickness", s.bin.wall_thickness},
            {"rgba", s.bin.rgba}}},
          {"width", s.width},
          {"height", s.height},
          {"seed", s.seed},
          {"skin", s.skin},
          {"sleeve", s.sleeve},
          {"initial_command", s.initial_command},
          {"timestep", s.timestep},
          {"substeps", s.substeps},
          {"msaa_samples", s.msaa_samples}};
}

SceneSpec scene_from_json(const nlohmann::json& j) {
  auto field = [&](const nlohmann::json& obj, const char* key) -> const nlohmann::json& {
    if (!obj.is_object() || !obj.contains(key))
      throw Error(std::string("scene json: missing field '") + key + "'");
    return obj.at(key);
  };
  try {
    SceneSpec s;
    s.embodiment = parse_embodiment(field(j, "embodiment").get<std::string>());
    for (const auto& jo : field(j, "objects")) {
      ObjectSpec o;
      o.shape = parse_shape(field(jo, "shape").get<std::string>());
      o.size = field(jo, "size").get<Vec3>();
      o.rgba = field(jo, "rgba").get<Rgba>();
      o.color = field(jo, "color").get<std::string>();
      o.mass = field(jo, "mass").get<double>();
      o.pos = field(jo, "pos").get<Vec3>();
      o.yaw = field(jo, "yaw").get<double>();
      s.objects.push_back(o);
    }
    s.background = field(j, "background").get<int>();
    const auto& l = field(j, "light");
    s.light.pos = field(l, "pos").get<Vec3>();
    s.light.dir = field(l, "dir").get<Vec3>();
    s.light.diffuse = field(l, "diffuse").get<Vec3>();
    s.light.ambient = field(l, "ambient").get<Vec3>();
    s.light.headlight = field(l, "headlight").get<Vec3>();
    const auto& c = field(j, "camera");
    s.camera.pos = field(c, "pos").get<Vec3>();
    s.camera.lookat = field(c, "lookat").get<Vec3>();
    s.camera.fovy = field(c, "fovy").get<double>();
    const auto& b = field(j, "bin");
    s.bin.enabled = field(b, "enabled").get<bool>();
    s.bin.center = field(b, "center").get<Vec3>();
    s.bin.half_x = field(b, "half_x").get<double>();
    s.bin.half_y = field(b, "half_y").get<double>();
    s.bin.wall_height = field(b, "wall_height").get<double>();
    s.bin.wall_thickness = field(b, "wall_thickness").get<double>();
    s.bin.rgba = field(b, "rgba").get<Rgba>();
    s.width = field(j, "width").get<int>();
    s.height = field(j, "height").get<int>();
    s.seed = field(j, "seed").get<uint64_t>();
    s.skin = field(j, "skin").get<Rgba>();
    s.sleeve = field(j, "sleeve").get<Rgba>();
    s.initial_command = field(j, "initial_command").get<std::vector<double>>();
    s.timestep = field(j, "timestep").get<double>();
    s.substeps = field(j, "substeps").get<int>();
    s.msaa_samples = field(j, "msaa_samples").get<int>();
    DOJO_CHECK(s.background >= 0 && s.background < kNumBackgrounds,
               "scene json: field 'background' out of range");
    return s;
  } catch (const nlohmann::json::exception& e) {
    throw Error(std::string("scene json: bad field type: ") + e.what());
  }
}

}  // namespace dojo::sim
