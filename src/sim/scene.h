// DojoSim scenes: a tabletop seen from an egocentric camera, with either a human hand or a robot
// arm, a set of objects and a background. A SceneSpec is plain data (sampled from a seed, or
// written by hand in tests) and build_mjcf() turns it into a MuJoCo 2.2 MJCF document.
//
// World frame: table top at z = 0, x to the right and y away from the camera (as seen in the
// image), z up. Lengths in metres, masses in kg, angles in radians.
//
// Object sets. The robot's data covers a narrow set (cubes and upright cylinders in red, green,
// blue); human data covers a wide set (ten shapes, eleven colours, varied sizes and masses).
// ObjectSet::kHumanOnly samples robot scenes with objects only the human set contains (the
// out-of-distribution "objects only humans touched" split). Backgrounds 0-5 are the training
// backgrounds; 6-8 are reserved for the "novel background" split and are never drawn by default.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace dojo::sim {

enum class Embodiment { kHuman, kRobot };

// Shape meanings of ObjectSpec::size (all half-extents / radii):
//   kBox       x, y, z half-extents          kSphere    radius
//   kCylinder  radius, half-height (upright) kCapsule   radius, half-length (lying along x)
//   kEllipsoid x, y, z radii                 kPlate     radius, half-thickness (flat disc)
//   kBottle    radius, body half-height (+ a neck on top)
//   kDumbbell  cube half-size, half-distance between the two cubes (bar along x)
//   kRing      ring radius, tube radius (torus of capsules lying flat)
//   kMug       radius, half-height (+ a handle on +x)
enum class Shape { kBox, kSphere, kCylinder, kCapsule, kEllipsoid, kPlate, kBottle, kDumbbell, kRing, kMug };
constexpr int kNumShapes = 10;

const char* to_string(Embodiment embodiment);
const char* to_string(Shape shape);
// Throws dojo::UsageError on an unknown name.
Embodiment parse_embodiment(const std::string& name);
Shape parse_shape(const std::string& name);

using Vec3 = std::array<double, 3>;
using Rgba = std::array<double, 4>;

struct ObjectSpec {
  Shape shape = Shape::kBox;
  Vec3 size{0.02, 0.02, 0.02};
  Rgba rgba{0.85, 0.15, 0.15, 1.0};
  std::string color = "red";  // colour word used in task texts
  double mass = 0.1;
  Vec3 pos{0.0, 0.0, 0.0};  // initial centre; build_mjcf() lifts z so the object rests on the table
  double yaw = 0.0;         // initial rotation about +z
};

// Lowest point of the object below its centre in its initial orientation (for placing on the
// table and for "on top of" computations).
double object_half_height(const ObjectSpec& object);
// Radius of a vertical cylinder around the centre that contains the object's footprint.
double object_footprint_radius(const ObjectSpec& object);
// True for objects of the robot's narrow set (red/green/blue cubes and cylinders).
bool in_robot_set(const ObjectSpec& object);
// "red box", "blue ring", ...
std::string object_description(const ObjectSpec& object);

struct CameraSpec {
  Vec3 pos{0.0, -0.34, 0.46};
  Vec3 lookat{0.0, 0.06, 0.0};
  double fovy = 52.0;  // vertical field of view, degrees
};

struct LightSpec {
  Vec3 pos{0.3, -0.3, 1.5};
  Vec3 dir{-0.2, 0.2, -1.0};
  Vec3 diffuse{0.7, 0.7, 0.7};
  Vec3 ambient{0.3, 0.3, 0.3};       // headlight ambient
  Vec3 headlight{0.25, 0.25, 0.25};  // headlight diffuse
};

// An open tray on the table. "Inside" = footprint within the inner walls.
struct BinSpec {
  bool enabled = false;
  Vec3 center{0.16, 0.14, 0.0};
  double half_x = 0.075;  // inner half-extents
  double half_y = 0.075;
  double wall_height = 0.03;
  double wall_thickness = 0.006;
  Rgba rgba{0.35, 0.35, 0.4, 1.0};
};

// The human's arm is drawn (visual only) from the wrist to a shoulder placed relative to the
// camera, like a right shoulder below and beside the eyes.
constexpr double kHumanForearmLen = 0.32;
constexpr double kHumanUpperArmLen = 0.34;
constexpr Vec3 kHumanShoulderFromCamera{0.19, -0.05, -0.2};

struct SceneSpec {
  Embodiment embodiment = Embodiment::kRobot;
  std::vector<ObjectSpec> objects;
  int background = 0;  // 0 .. kNumBackgrounds-1
  LightSpec light;
  CameraSpec camera;
  BinSpec bin;
  int width = 64;
  int height = 64;
  uint64_t seed = 0;
  // Human hand only: skin and sleeve colours.
  Rgba skin{0.87, 0.68, 0.56, 1.0};
  Rgba sleeve{0.2, 0.3, 0.55, 1.0};
  // Initial command (see World::step); empty = the embodiment's default rest pose.
  std::vector<double> initial_command;
  // Physics: control runs at 1 / (timestep * substeps) Hz = 10 Hz by default.
  double timestep = 0.004;
  int substeps = 25;
  // Anti-aliasing samples of the offscreen buffer (0 = off).
  int msaa_samples = 4;
};

constexpr int kNumBackgrounds = 9;
constexpr int kNumTrainBackgrounds = 6;  // ids 0-5; ids 6-8 are the novel-background split

enum class ObjectSet {
  kDefault,    // the embodiment's own set (robot: narrow, human: wide)
  kRobot,      // cubes and cylinders in red/green/blue
  kHuman,      // the wide set (includes the robot objects)
  kHumanOnly,  // wide-set objects that are not in the robot set (OOD split); graspable sizes
};
enum class BackgroundSplit {
  kDefault,  // robot: backgrounds 0-1 (narrow); human: 0-5
  kTrain,    // 0-5
  kNovel,    // 6-8
  kAny,      // 0-8
};

struct SceneSampling {
  int min_objects = -1;  // -1: robot 1, human 1
  int max_objects = -1;  // -1: robot 3, human 4
  ObjectSet object_set = ObjectSet::kDefault;
  BackgroundSplit backgrounds = BackgroundSplit::kDefault;
  int width = 64;
  int height = 64;
  double bin_probability = -1.0;  // -1: robot 1.0, human 0.3
  double camera_jitter = -1.0;    // metres; -1: robot 0.0, human 0.03
};

// Samples a scene; a pure function of its arguments. Throws dojo::UsageError on bad options.
SceneSpec sample_scene(Embodiment embodiment, const SceneSampling& options, uint64_t seed);

// The MJCF document for a scene. Body names: "obj0".."objN-1" (free joints "obj0_joint"...),
// camera "ego", robot joints base_yaw/shoulder/elbow/wrist_pitch/wrist_roll/finger_l/finger_r,
// hand joints hand_x/hand_y/hand_z/hand_yaw/hand_pitch and finger hinges.
std::string build_mjcf(const SceneSpec& spec);

// Short name of a background ("oak", "checker-grey", ...).
std::string background_name(int background);

nlohmann::json to_json(const ObjectSpec& object);
nlohmann::json to_json(const SceneSpec& spec);
// Inverse of to_json(SceneSpec); throws dojo::Error naming the missing/bad field.
SceneSpec scene_from_json(const nlohmann::json& json);

}  // namespace dojo::sim
