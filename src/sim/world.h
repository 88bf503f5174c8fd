// A DojoSim world: one MuJoCo model + data built from a SceneSpec, stepped at the control rate.
//
// Commands (World::step). Both embodiments take a 6-vector, held for one control step (0.1 s at
// the default 10 Hz) and linearly interpolated from the previous command across the physics
// substeps so position targets change smoothly:
//   robot: [base_yaw, shoulder, elbow, wrist_pitch, wrist_roll, gripper]  joint targets (rad) and
//          gripper opening fraction in [0, 1] (1 = open). See robot_arm.h.
//   human: [x, y, z, yaw, pitch, curl]  palm centre in world metres, yaw about +z (0 = fingers
//          along +y), pitch (positive tilts the fingers down) and finger curl in [0, 1].
// Commands are clamped to the joint ranges. The embodiment's joints are gravity compensated
// (qfrc_applied = qfrc_bias each substep), so the position servos track without sag.
//
// Grasping. Robot grasps are purely frictional (finger pads squeeze the object). The human hand
// has a grasp assist: when the commanded curl is >= 0.5 and an object touches the hand inside
// the region under the palm, a weld equality fixes it to the hand at its current relative pose;
// it is released when curl drops below 0.35. This keeps human pick/stack clips looking right
// without a dexterous-hand controller; human clips carry no actions, so nothing learns from it.
//
// Thread-safety: a World is not thread-safe; different Worlds may be used on different threads
// (model compilation is serialized internally).
//
// Errors: the first World installs process-wide MuJoCo error/warning handlers that raise
// dojo::Error / log a warning instead of exiting or writing MUJOCO_LOG.TXT.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "sim/scene.h"

struct mjModel_;
struct mjData_;

namespace dojo::sim {

// A point seen by the ego camera: (u, v) normalised to [0, 1] over the image (u to the right, v
// down; 0 and 1 are the image edges), in_view when it lies in front of the camera and inside the
// image. Occlusion is not considered.
struct ImagePoint {
  double u = 0, v = 0;
  bool in_view = false;
};

struct ObjectPose {
  Vec3 pos{};                    // world position of the body frame (the object's centre)
  std::array<double, 4> quat{};  // world orientation, MuJoCo order (w, x, y, z)
  Vec3 linvel{};                 // world linear velocity, m/s
  Vec3 angvel{};                 // angular velocity (body frame), rad/s
};

class World {
 public:
  // Builds the MJCF and compiles it; throws dojo::Error with MuJoCo's message on failure.
  explicit World(const SceneSpec& spec);
  ~World();
  World(const World&) = delete;
  World& operator=(const World&) = delete;

  // Back to the initial state: objects at their spec poses (resting on the table), the
  // embodiment at the initial command, time 0. The constructor calls it.
  void reset();
  // One control step with `command` (size action_dim()); throws dojo::Error on a wrong size,
  // non-finite values, or if the physics diverges.
  void step(const std::vector<double>& command);
  // `steps` control steps holding the last command (used to let objects settle).
  void hold(int steps);

  const SceneSpec& spec() const { return spec_; }
  Embodiment embodiment() const { return spec_.embodiment; }
  int action_dim() const { return 6; }
  int state_dim() const { return 6; }
  std::vector<std::string> command_names() const;
  std::vector<std::string> state_names() const;
  // The command that holds the embodiment at its rest pose.
  const std::vector<double>& initial_command() const { return initial_command_; }
  const std::vector<double>& last_command() const { return last_command_; }
  // Measured state, same layout as the command: robot joint angles + gripper opening fraction;
  // human hand pose + measured curl.
  std::vector<double> state() const;
  // Robot: [x, y, z, closing_yaw, gripper] of the grasp point (for hidden-motion logging);
  // human: the hand pose part of state().
  std::vector<double> effector_pose() const;
  // Point where a grasped object sits: between the robot's finger pads / under the human palm.
  Vec3 grasp_point() const;

  // Where a world point appears in the ego camera's image, from the same kinematic state the
  // renderer draws (so a frame and the keypoints recorded with it agree).
  ImagePoint project(const Vec3& point) const;
  // The embodiment's keypoints in the image, for pose probes and action-following metrics:
  // robot gripper (grasp point), wrist (wrist pitch axis), elbow; human palm, index finger (its
  // last joint), thumb (its last joint). Names in keypoint_names() order.
  std::vector<ImagePoint> keypoints() const;
  std::vector<std::string> keypoint_names() const;

  int num_objects() const { return static_cast<int>(spec_.objects.size()); }
  ObjectPose object_pose(int index) const;
  std::vector<ObjectPose> object_poses() const;
  // Lowest and highest world z of the object's collision geometry in its current pose.
  std::array<double, 2> object_z_range(int index) const;
  // Teleports an object (zero velocity) and recomputes derived quantities; for tests and
  // hand-made states.
  void set_object_pose(int index, const Vec3& pos, const std::array<double, 4>& quat = {1, 0, 0, 0});
  // Human grasp assist: index of the welded object or -1.
  int grasped_object() const { return grasped_; }
  // Robot: true when any finger pad touches object `index`. Human: any hand geom touches it.
  bool touching(int index) const;

  double sim_time() const;
  int64_t control_steps() const { return control_steps_; }
  double control_dt() const { return spec_.timestep * spec_.substeps; }
  // Unique per World instance (renderers cache GPU-side state per world).
  uint64_t id() const { return id_; }

  const mjModel_* model() const { return model_; }
  mjData_* data() { return data_; }
  const mjData_* data() const { return data_; }

 private:
  void command_to_ctrl(const std::vector<double>& command, std::vector<double>* ctrl) const;
  std::vector<double> clamp_command(const std::vector<double>& command) const;
  void update_grasp_assist(const std::vector<double>& command);
  void check_stable() const;
  void pose_human_arm();

  SceneSpec spec_;
  mjModel_* model_ = nullptr;
  mjData_* data_ = nullptr;
  uint64_t id_;
  std::vector<double> initial_command_;
  std::vector<double> last_command_;
  int64_t control_steps_ = 0;
  int grasped_ = -1;
  // Indices into the model.
  std::vector<int> object_body_;
  std::vector<int> object_qpos_;
  std::vector<int> object_dof_;
  std::vector<int> actuated_qpos_;  // per actuator, the qpos address of its joint
  std::vector<int> embodiment_dofs_;
  std::vector<int> effector_geoms_;  // robot: finger pads; human: all hand geoms
  int root_body_ = -1;               // human: "hand"; robot: "arm_hand"
  int grasp_site_ = -1;
  std::vector<int> weld_eq_;
  int forearm_mocap_ = -1, upper_arm_mocap_ = -1;
  int camera_ = -1;
  std::vector<int> keypoint_bodies_;  // wrist and elbow (robot) / palm, index, thumb (human) bodies
};

}  // namespace dojo::sim
