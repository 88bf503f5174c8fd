// DojoSim scenes: shape and embodiment names, object geometry helpers, background names and
// the JSON form of a SceneSpec. The MJCF writer is in scene_mjcf.cpp, sampling in
// scene_sampling.cpp.
#include "sim/scene.h"

#include <algorithm>
#include <cmath>
#include <string>

#include <nlohmann/json.hpp>

#include "core/error.h"
#include "sim/scene_internal.h"

namespace dojo::sim {

// Shared with the MJCF writer and the sampler (scene_internal.h).
Vec3 normalized(const Vec3& v) {
  const double n = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  return {v[0] / n, v[1] / n, v[2] / n};
}

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
