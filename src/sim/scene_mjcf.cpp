// The MJCF writer for DojoSim scenes: build_mjcf() and the writers of its parts (textures,
// objects, the robot arm, the human hand, the bin).
#include "sim/scene.h"

#include <cmath>
#include <cstdio>
#include <sstream>
#include <string>

#include "core/error.h"
#include "sim/robot_arm.h"
#include "sim/scene_internal.h"

namespace dojo::sim {
namespace {

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

}  // namespace

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
    << "\" fovy=\"" << num(spec.camera.fovy) << "\"/>\n";
  // A second, fixed view from the table's right (multi-view datasets, `sim generate --cameras
  // ego,side`): it sees the arm's reach along y, which the ego view sees foreshortened.
  const Vec3 side_pos{0.62, 0.10, 0.30}, side_lookat{0.0, 0.10, 0.04};
  const Vec3 sf =
      normalized({side_lookat[0] - side_pos[0], side_lookat[1] - side_pos[1], side_lookat[2] - side_pos[2]});
  const Vec3 side_right = normalized(cross(sf, {0, 0, 1}));
  x << "    <camera name=\"side\" pos=\"" << vec(side_pos) << "\" xyaxes=\"" << vec(side_right) << " "
    << vec(cross(side_right, sf)) << "\" fovy=\"55\"/>\n"
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

}  // namespace dojo::sim
