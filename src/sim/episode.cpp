#include "sim/episode.h"

#include <cmath>
#include <memory>

#include "core/error.h"
#include "sim/renderer.h"
#include "sim/task.h"
#include "sim/world.h"

namespace dojo::sim {
namespace {

std::vector<float> to_float(const std::vector<double>& v) { return std::vector<float>(v.begin(), v.end()); }

}  // namespace

ControllerSpec default_controller(Embodiment embodiment) {
  ControllerSpec c;
  c.kind = embodiment == Embodiment::kHuman ? ControllerKind::kHumanSkill : ControllerKind::kRobotPolicy;
  return c;
}

EpisodeRecord run_episode(const EpisodeSpec& spec, Renderer* renderer) {
  DOJO_CHECK(spec.num_steps >= 1, "episode: num_steps must be >= 1");
  DOJO_CHECK(spec.settle_steps >= 0 && spec.final_settle_steps >= 0, "episode: settle steps must be >= 0");
  const bool human = spec.scene.embodiment == Embodiment::kHuman;
  DOJO_CHECK(human == (spec.controller.kind == ControllerKind::kHumanSkill),
             std::string("episode: controller kind does not match the ") + to_string(spec.scene.embodiment) +
                 " embodiment");
  World world(spec.scene);
  std::unique_ptr<Controller> controller =
      human ? make_human_controller(world, spec.controller.human, spec.seed)
            : make_robot_controller(world, spec.controller.robot, spec.seed);
  if (spec.render && !renderer) {
    thread_local std::unique_ptr<Renderer> local;
    if (!local) local = std::make_unique<Renderer>();
    renderer = local.get();
  }

  world.hold(spec.settle_steps);
  const std::vector<ObjectPose> initial = world.object_poses();

  EpisodeRecord rec;
  rec.width = spec.scene.width;
  rec.height = spec.scene.height;
  const int T = spec.num_steps;
  if (spec.render) rec.frames.reserve(T);
  for (const auto& camera : spec.extra_cameras) rec.views.push_back({camera, {}});
  for (int t = 0; t < T; ++t) {
    if (spec.render) {
      rec.frames.push_back(renderer->render(world));
      for (auto& [camera, frames] : rec.views) frames.push_back(renderer->render(world, camera.c_str()));
    }
    std::vector<float> points;
    for (const auto& p : world.keypoints())
      points.insert(points.end(), {static_cast<float>(p.u), static_cast<float>(p.v), p.in_view ? 1.f : 0.f});
    rec.keypoints.push_back(std::move(points));
    const std::vector<double> state = world.state();
    const std::vector<double> command = controller->act(world, t);
    if (human) {
      rec.hidden_motion.push_back(to_float(command));
    } else {
      rec.states.push_back(to_float(state));
      rec.actions.push_back(to_float(command));
      rec.hidden_motion.push_back(to_float(world.effector_pose()));
    }
    world.step(command);
  }
  world.hold(spec.final_settle_steps);
  if (!human && spec.scene.bin.enabled) rec.success = bin_success(world);

  bool ood = false;
  for (const auto& o : spec.scene.objects) ood |= !in_robot_set(o);
  nlohmann::json& m = rec.meta;
  m["embodiment"] = to_string(spec.scene.embodiment);
  m["task"] = controller->task_text();
  m["controller"] = controller->describe();
  // Flat list of what happened: human skill names in order, or the robot behaviour.
  nlohmann::json skills = nlohmann::json::array();
  if (human) {
    for (const auto& s : m["controller"]["skills"]) skills.push_back(s["skill"]);
  } else {
    skills.push_back(m["controller"]["behavior"]);
  }
  m["skills"] = skills;
  m["scene"] = to_json(spec.scene);
  m["background"] = spec.scene.background;
  m["novel_background"] = spec.scene.background >= kNumTrainBackgrounds;
  m["ood_objects"] = ood;
  m["fps"] = 1.0 / world.control_dt();
  m["num_steps"] = T;
  m["seed"] = spec.seed;
  m["scene_seed"] = spec.scene.seed;
  m["width"] = spec.scene.width;
  m["height"] = spec.scene.height;
  m["action_names"] = human ? nlohmann::json::array() : nlohmann::json(world.command_names());
  m["state_names"] = human ? nlohmann::json::array() : nlohmann::json(world.state_names());
  m["hidden_motion_names"] =
      human ? nlohmann::json(world.command_names())
            : nlohmann::json({"grasp_x", "grasp_y", "grasp_z", "closing_yaw", "gripper"});
  m["keypoint_names"] = world.keypoint_names();
  m["object_outcomes"] = object_outcomes(world, initial);
  m["success"] = std::isnan(rec.success) ? nlohmann::json(nullptr) : nlohmann::json(rec.success);
  return rec;
}

}  // namespace dojo::sim
