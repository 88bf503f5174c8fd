#include "sim/world.h"

#include <mujoco/mujoco.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <memory>
#include <mutex>

#include "core/error.h"
#include "core/log.h"
#include "sim/robot_arm.h"

namespace dojo::sim {
namespace {

std::atomic<uint64_t> g_next_world_id{1};

// MuJoCo's default error handler exits the process and its warning handler writes
// MUJOCO_LOG.TXT into the working directory; route both through our error/log machinery.
void mujoco_error(const char* message) { throw Error(std::string("MuJoCo: ") + message); }
void mujoco_warning(const char* message) { LOG_WARN("MuJoCo: ", message); }

void install_mujoco_handlers() {
  static std::once_flag once;
  std::call_once(once, [] {
    mju_user_error = mujoco_error;
    mju_user_warning = mujoco_warning;
  });
}

mjModel* load_model(const std::string& xml) {
  install_mujoco_handlers();
  // The XML compiler keeps global state; serialize loads across threads.
  static std::mutex load_mutex;
  std::lock_guard<std::mutex> lock(load_mutex);
  auto vfs = std::make_unique<mjVFS>();  // ~2 MB: keep it off the stack
  mj_defaultVFS(vfs.get());
  const char* name = "dojosim_scene.xml";
  if (mj_makeEmptyFileVFS(vfs.get(), name, static_cast<int>(xml.size())) != 0) {
    throw Error("DojoSim: could not allocate the in-memory MJCF file");
  }
  const int index = mj_findFileVFS(vfs.get(), name);
  std::memcpy(vfs->filedata[index], xml.data(), xml.size());
  char error[1024] = {0};
  mjModel* model = mj_loadXML(name, vfs.get(), error, sizeof(error));
  mj_deleteVFS(vfs.get());
  if (!model) throw Error(std::string("DojoSim: MJCF did not compile: ") + error);
  return model;
}

int require_id(const mjModel* m, int type, const std::string& name) {
  const int id = mj_name2id(m, type, name.c_str());
  DOJO_CHECK(id >= 0, "DojoSim: model has no element named '" + name + "'");
  return id;
}

// Finger joint targets for a curl fraction (proximal, distal, thumb proximal, thumb distal).
constexpr double kCurlJ1 = 1.35, kCurlJ2 = 1.5, kThumbJ1 = 1.0, kThumbJ2 = 0.7;
// Grasp assist hysteresis on the commanded curl.
constexpr double kGraspCurl = 0.5, kReleaseCurl = 0.35;

// Relative pose of body b in the frame of body a: position and quaternion.
void relative_pose(const mjData* d, int a, int b, mjtNum pos[3], mjtNum quat[4]) {
  mjtNum diff[3];
  mju_sub3(diff, d->xpos + 3 * b, d->xpos + 3 * a);
  mju_mulMatTVec(pos, d->xmat + 9 * a, diff, 3, 3);
  mjtNum inv[4];
  mju_negQuat(inv, d->xquat + 4 * a);
  mju_mulQuat(quat, inv, d->xquat + 4 * b);
}

}  // namespace

World::World(const SceneSpec& spec) : spec_(spec), id_(g_next_world_id.fetch_add(1)) {
  model_ = load_model(build_mjcf(spec_));
  data_ = mj_makeData(model_);
  if (!data_) {
    mj_deleteModel(model_);
    throw Error("DojoSim: mj_makeData failed");
  }
  const mjModel* m = model_;
  for (int i = 0; i < num_objects(); ++i) {
    const int body = require_id(m, mjOBJ_BODY, "obj" + std::to_string(i));
    const int joint = require_id(m, mjOBJ_JOINT, "obj" + std::to_string(i) + "_joint");
    object_body_.push_back(body);
    object_qpos_.push_back(m->jnt_qposadr[joint]);
    object_dof_.push_back(m->jnt_dofadr[joint]);
  }
  for (int a = 0; a < m->nu; ++a) actuated_qpos_.push_back(m->jnt_qposadr[m->actuator_trnid[2 * a]]);
  // Every non-free joint belongs to the embodiment.
  for (int j = 0; j < m->njnt; ++j) {
    if (m->jnt_type[j] != mjJNT_FREE) embodiment_dofs_.push_back(m->jnt_dofadr[j]);
  }
  camera_ = require_id(m, mjOBJ_CAMERA, "ego");
  if (spec_.embodiment == Embodiment::kRobot) {
    root_body_ = require_id(m, mjOBJ_BODY, "arm_hand");
    grasp_site_ = require_id(m, mjOBJ_SITE, "grasp");
    keypoint_bodies_ = {require_id(m, mjOBJ_BODY, "arm_wrist"), require_id(m, mjOBJ_BODY, "arm_fore")};
    for (const char* finger : {"finger_l", "finger_r"}) {
      const int body = require_id(m, mjOBJ_BODY, finger);
      for (int g = 0; g < m->ngeom; ++g) {
        if (m->geom_bodyid[g] == body) effector_geoms_.push_back(g);
      }
    }
    const arm::Joints home = arm::home_joints();
    initial_command_.assign(home.begin(), home.end());
    initial_command_.push_back(1.0);
  } else {
    root_body_ = require_id(m, mjOBJ_BODY, "hand");
    keypoint_bodies_ = {root_body_, require_id(m, mjOBJ_BODY, "f1_dist"),
                        require_id(m, mjOBJ_BODY, "thumb_dist")};
    for (int g = 0; g < m->ngeom; ++g) {
      // The hand subtree: bodies whose root ancestor is the hand body.
      if (m->body_rootid[m->geom_bodyid[g]] == root_body_ && m->geom_contype[g] != 0)
        effector_geoms_.push_back(g);
    }
    for (int i = 0; i < num_objects(); ++i) {
      weld_eq_.push_back(require_id(m, mjOBJ_EQUALITY, "grasp" + std::to_string(i)));
    }
    initial_command_ = {0.1, -0.2, 0.15, 0.25, 0.0, 0.25};
    forearm_mocap_ = m->body_mocapid[require_id(m, mjOBJ_BODY, "forearm_vis")];
    upper_arm_mocap_ = m->body_mocapid[require_id(m, mjOBJ_BODY, "upper_arm_vis")];
  }
  if (!spec_.initial_command.empty()) {
    DOJO_CHECK(static_cast<int>(spec_.initial_command.size()) == action_dim(),
               "scene: initial_command has " + std::to_string(spec_.initial_command.size()) +
                   " values, expected " + std::to_string(action_dim()));
    initial_command_ = spec_.initial_command;
  }
  initial_command_ = clamp_command(initial_command_);
  reset();
}

World::~World() {
  if (data_) mj_deleteData(data_);
  if (model_) mj_deleteModel(model_);
}

std::vector<std::string> World::command_names() const {
  if (spec_.embodiment == Embodiment::kRobot) {
    return {"base_yaw", "shoulder", "elbow", "wrist_pitch", "wrist_roll", "gripper"};
  }
  return {"hand_x", "hand_y", "hand_z", "hand_yaw", "hand_pitch", "hand_curl"};
}

std::vector<std::string> World::state_names() const { return command_names(); }

std::vector<double> World::clamp_command(const std::vector<double>& c) const {
  std::vector<double> out = c;
  if (spec_.embodiment == Embodiment::kRobot) {
    for (int j = 0; j < arm::kNumArmJoints; ++j) {
      out[j] = std::clamp(out[j], arm::kJointLimits[j].lo, arm::kJointLimits[j].hi);
    }
    out[5] = std::clamp(out[5], 0.0, 1.0);
  } else {
    out[0] = std::clamp(out[0], -0.45, 0.45);
    out[1] = std::clamp(out[1], -0.5, 0.4);
    out[2] = std::clamp(out[2], 0.0, 0.5);
    out[3] = std::clamp(out[3], -2.6, 2.6);
    out[4] = std::clamp(out[4], -0.6, 1.3);
    out[5] = std::clamp(out[5], 0.0, 1.0);
  }
  return out;
}

void World::command_to_ctrl(const std::vector<double>& c, std::vector<double>* ctrl) const {
  ctrl->assign(model_->nu, 0.0);
  if (spec_.embodiment == Embodiment::kRobot) {
    for (int j = 0; j < 5; ++j) (*ctrl)[j] = c[j];
    (*ctrl)[5] = (*ctrl)[6] = c[5] * arm::kFingerTravel;
  } else {
    for (int j = 0; j < 5; ++j) (*ctrl)[j] = c[j];
    for (int f = 0; f < 4; ++f) {
      (*ctrl)[5 + 2 * f] = c[5] * kCurlJ1;
      (*ctrl)[6 + 2 * f] = c[5] * kCurlJ2;
    }
    (*ctrl)[13] = c[5] * kThumbJ1;
    (*ctrl)[14] = c[5] * kThumbJ2;
  }
}

void World::reset() {
  mjModel* m = model_;
  mjData* d = data_;
  mj_resetData(m, d);
  for (int eq : weld_eq_) m->eq_active[eq] = 0;
  grasped_ = -1;
  // Start the embodiment exactly at its initial command so nothing jumps at t = 0.
  std::vector<double> ctrl;
  command_to_ctrl(initial_command_, &ctrl);
  for (int a = 0; a < m->nu; ++a) {
    d->qpos[actuated_qpos_[a]] = ctrl[a];
    d->ctrl[a] = ctrl[a];
  }
  last_command_ = initial_command_;
  control_steps_ = 0;
  mj_forward(m, d);
  pose_human_arm();
}

namespace {
// Quaternion rotating +z onto the unit vector v.
void quat_z_to(const mjtNum v[3], mjtNum q[4]) {
  const mjtNum z[3] = {0, 0, 1};
  mjtNum axis[3];
  mju_cross(axis, z, v);
  const mjtNum s = mju_normalize3(axis), c = v[2];
  if (s < 1e-9) {
    q[0] = c > 0 ? 1 : 0;
    q[1] = c > 0 ? 0 : 1;
    q[2] = q[3] = 0;
    return;
  }
  mju_axisAngle2Quat(q, axis, std::atan2(s, c));
}
}  // namespace

void World::pose_human_arm() {
  if (forearm_mocap_ < 0) return;
  mjData* d = data_;
  // Wrist: back edge of the palm, in world coordinates.
  const mjtNum local[3] = {0.001, -0.066, 0.007};
  mjtNum wrist[3];
  mju_mulMatVec(wrist, d->xmat + 9 * root_body_, local, 3, 3);
  mju_addTo3(wrist, d->xpos + 3 * root_body_);
  mjtNum shoulder[3];
  for (int k = 0; k < 3; ++k) shoulder[k] = spec_.camera.pos[k] + kHumanShoulderFromCamera[k];
  // Two-link arm with the elbow bent down and out to the right. When the hand is out of reach
  // the shoulder leans toward it, as a person would.
  const double l1 = kHumanUpperArmLen, l2 = kHumanForearmLen;
  mjtNum axis[3];
  mju_sub3(axis, wrist, shoulder);
  double dist = mju_normalize3(axis);
  const double max_reach = l1 + l2 - 0.005;
  if (dist > max_reach) {
    mju_addToScl3(shoulder, axis, dist - max_reach);
    dist = max_reach;
  }
  dist = std::max(dist, std::fabs(l1 - l2) + 0.01);
  const double a = (l1 * l1 - l2 * l2 + dist * dist) / (2 * dist);
  const double h = std::sqrt(std::max(0.0, l1 * l1 - a * a));
  mjtNum pole[3] = {0.6, -0.15, -0.75};
  mju_addToScl3(pole, axis, -mju_dot3(pole, axis));
  mju_normalize3(pole);
  mjtNum elbow[3];
  for (int k = 0; k < 3; ++k) elbow[k] = shoulder[k] + a * axis[k] + h * pole[k];
  mjtNum dir[3];
  mju_sub3(dir, elbow, shoulder);
  mju_normalize3(dir);
  mju_copy3(d->mocap_pos + 3 * upper_arm_mocap_, shoulder);
  quat_z_to(dir, d->mocap_quat + 4 * upper_arm_mocap_);
  mju_sub3(dir, wrist, elbow);
  mju_normalize3(dir);
  mju_copy3(d->mocap_pos + 3 * forearm_mocap_, elbow);
  quat_z_to(dir, d->mocap_quat + 4 * forearm_mocap_);
  // Refresh body/geom poses so a render right now shows the arm where it belongs.
  mj_kinematics(model_, d);
}

void World::update_grasp_assist(const std::vector<double>& command) {
  if (spec_.embodiment != Embodiment::kHuman || weld_eq_.empty()) return;
  mjModel* m = model_;
  const mjData* d = data_;
  const double curl = command[5];
  if (grasped_ >= 0 && curl < kReleaseCurl) {
    m->eq_active[weld_eq_[grasped_]] = 0;
    grasped_ = -1;
    return;
  }
  if (grasped_ >= 0 || curl < kGraspCurl) return;
  int best = -1;
  double best_dist = 1e9;
  const double palm_bottom = d->xpos[3 * root_body_ + 2] - 0.011;
  for (int i = 0; i < num_objects(); ++i) {
    // Touching the hand, or just below the palm: curling fingers on a flat object press on the
    // table and lift the palm a few millimetres off it.
    if (!touching(i) && object_z_range(i)[1] < palm_bottom - 0.015) continue;
    mjtNum local[3], quat[4];
    relative_pose(d, root_body_, object_body_[i], local, quat);
    // Under the palm, where the curled fingers and thumb close (not under the outstretched
    // fingertips), and below it.
    if (std::fabs(local[0]) > 0.06 || local[1] < -0.05 || local[1] > 0.065 || local[2] > 0.0 ||
        local[2] < -0.1)
      continue;
    const double dist = std::hypot(local[0], local[1] - 0.02);
    if (dist < best_dist) {
      best_dist = dist;
      best = i;
    }
  }
  if (best < 0) return;
  // Weld data (MuJoCo 2.2): anchor[3] in body2, relpose pos[3] + quat[4] of body2 in body1,
  // torquescale. Freeze the current relative pose so the object does not jump.
  mjtNum* data = m->eq_data + mjNEQDATA * weld_eq_[best];
  mjtNum pos[3], quat[4];
  relative_pose(d, root_body_, object_body_[best], pos, quat);
  data[0] = data[1] = data[2] = 0;
  mju_copy3(data + 3, pos);
  mju_copy4(data + 6, quat);
  data[10] = 1;
  m->eq_active[weld_eq_[best]] = 1;
  grasped_ = best;
}

void World::step(const std::vector<double>& command_in) {
  DOJO_CHECK(static_cast<int>(command_in.size()) == action_dim(),
             "World::step: command has " + std::to_string(command_in.size()) + " values, expected " +
                 std::to_string(action_dim()));
  for (double v : command_in)
    DOJO_CHECK(std::isfinite(v), "World::step: command contains a non-finite value");
  const std::vector<double> command = clamp_command(command_in);
  update_grasp_assist(command);
  std::vector<double> from, to;
  command_to_ctrl(last_command_, &from);
  command_to_ctrl(command, &to);
  mjModel* m = model_;
  mjData* d = data_;
  const int n = spec_.substeps;
  for (int k = 1; k <= n; ++k) {
    const double alpha = static_cast<double>(k) / n;
    for (int a = 0; a < m->nu; ++a) d->ctrl[a] = from[a] + alpha * (to[a] - from[a]);
    mj_step1(m, d);
    for (int dof : embodiment_dofs_) d->qfrc_applied[dof] = d->qfrc_bias[dof];
    mj_step2(m, d);
  }
  last_command_ = command;
  ++control_steps_;
  check_stable();
  pose_human_arm();
}

void World::hold(int steps) {
  const std::vector<double> c = last_command_;
  for (int i = 0; i < steps; ++i) step(c);
}

void World::check_stable() const {
  const mjData* d = data_;
  const int bad = d->warning[mjWARN_BADQACC].number + d->warning[mjWARN_BADQVEL].number +
                  d->warning[mjWARN_BADQPOS].number;
  if (bad > 0) {
    throw Error("DojoSim: physics diverged at t=" + std::to_string(d->time) + " s (scene seed " +
                std::to_string(spec_.seed) + ")");
  }
  if (d->warning[mjWARN_CONTACTFULL].number > 0 || d->warning[mjWARN_CNSTRFULL].number > 0) {
    throw Error("DojoSim: contact/constraint buffer full (scene seed " + std::to_string(spec_.seed) + ")");
  }
}

std::vector<double> World::state() const {
  const mjData* d = data_;
  std::vector<double> s(6);
  if (spec_.embodiment == Embodiment::kRobot) {
    for (int j = 0; j < 5; ++j) s[j] = d->qpos[actuated_qpos_[j]];
    s[5] = (d->qpos[actuated_qpos_[5]] + d->qpos[actuated_qpos_[6]]) / (2.0 * arm::kFingerTravel);
  } else {
    for (int j = 0; j < 5; ++j) s[j] = d->qpos[actuated_qpos_[j]];
    double curl = 0;
    for (int f = 0; f < 4; ++f) curl += d->qpos[actuated_qpos_[5 + 2 * f]] / kCurlJ1;
    s[5] = curl / 4.0;
  }
  return s;
}

std::vector<double> World::effector_pose() const {
  if (spec_.embodiment == Embodiment::kHuman) return state();
  const Vec3 p = grasp_point();
  const std::vector<double> s = state();
  return {p[0], p[1], p[2], s[0] - s[4], s[5]};
}

Vec3 World::grasp_point() const {
  const mjData* d = data_;
  if (grasp_site_ >= 0)
    return {d->site_xpos[3 * grasp_site_], d->site_xpos[3 * grasp_site_ + 1],
            d->site_xpos[3 * grasp_site_ + 2]};
  // Human: 3 cm below the palm centre, slightly toward the fingers.
  const mjtNum local[3] = {0.0, 0.015, -0.03};
  mjtNum world[3];
  mju_mulMatVec(world, d->xmat + 9 * root_body_, local, 3, 3);
  return {d->xpos[3 * root_body_] + world[0], d->xpos[3 * root_body_ + 1] + world[1],
          d->xpos[3 * root_body_ + 2] + world[2]};
}

ImagePoint World::project(const Vec3& point) const {
  const mjData* d = data_;
  // MuJoCo cameras look along their -z axis, x to the image's right and y up; cam_xmat holds
  // those axes as the columns of a row-major 3x3 rotation.
  const mjtNum* pos = d->cam_xpos + 3 * camera_;
  const mjtNum* axes = d->cam_xmat + 9 * camera_;
  const mjtNum rel[3] = {point[0] - pos[0], point[1] - pos[1], point[2] - pos[2]};
  mjtNum c[3];
  mju_mulMatTVec(c, axes, rel, 3, 3);
  ImagePoint p;
  const double depth = -c[2];
  if (depth <= 1e-6) return p;  // behind the camera
  // The vertical field of view sets the focal length; pixels are square.
  const double h = spec_.height, w = spec_.width;
  const double focal = 0.5 * h / std::tan(0.5 * model_->cam_fovy[camera_] * M_PI / 180.0);
  p.u = (0.5 * w + focal * c[0] / depth) / w;
  p.v = (0.5 * h - focal * c[1] / depth) / h;
  p.in_view = p.u >= 0 && p.u <= 1 && p.v >= 0 && p.v <= 1;
  return p;
}

std::vector<ImagePoint> World::keypoints() const {
  const mjData* d = data_;
  std::vector<ImagePoint> out;
  if (spec_.embodiment == Embodiment::kRobot) out.push_back(project(grasp_point()));
  for (int b : keypoint_bodies_)
    out.push_back(project({d->xpos[3 * b], d->xpos[3 * b + 1], d->xpos[3 * b + 2]}));
  return out;
}

std::vector<std::string> World::keypoint_names() const {
  if (spec_.embodiment == Embodiment::kRobot) return {"gripper", "wrist", "elbow"};
  return {"palm", "index", "thumb"};
}

ObjectPose World::object_pose(int index) const {
  DOJO_CHECK(index >= 0 && index < num_objects(),
             "World: object index " + std::to_string(index) + " out of range");
  const mjData* d = data_;
  const int b = object_body_[index];
  const int v = object_dof_[index];
  ObjectPose p;
  for (int k = 0; k < 3; ++k) {
    p.pos[k] = d->xpos[3 * b + k];
    p.linvel[k] = d->qvel[v + k];
    p.angvel[k] = d->qvel[v + 3 + k];
  }
  for (int k = 0; k < 4; ++k) p.quat[k] = d->xquat[4 * b + k];
  return p;
}

std::vector<ObjectPose> World::object_poses() const {
  std::vector<ObjectPose> out;
  for (int i = 0; i < num_objects(); ++i) out.push_back(object_pose(i));
  return out;
}

std::array<double, 2> World::object_z_range(int index) const {
  DOJO_CHECK(index >= 0 && index < num_objects(),
             "World: object index " + std::to_string(index) + " out of range");
  const mjModel* m = model_;
  const mjData* d = data_;
  const int body = object_body_[index];
  double lo = 1e9, hi = -1e9;
  for (int g = m->body_geomadr[body]; g < m->body_geomadr[body] + m->body_geomnum[body]; ++g) {
    if (m->geom_contype[g] == 0) continue;
    const mjtNum* size = m->geom_size + 3 * g;
    const mjtNum* R = d->geom_xmat + 9 * g;  // row-major; row 2 = world z of the local axes
    const double ax = std::fabs(R[6]), ay = std::fabs(R[7]), az = std::fabs(R[8]);
    double extent = 0;
    switch (m->geom_type[g]) {
      case mjGEOM_SPHERE:
        extent = size[0];
        break;
      case mjGEOM_CAPSULE:
        extent = az * size[1] + size[0];
        break;
      case mjGEOM_CYLINDER:
        extent = az * size[1] + size[0] * std::sqrt(std::max(0.0, 1 - az * az));
        break;
      case mjGEOM_ELLIPSOID:
        extent = std::sqrt(std::pow(ax * size[0], 2) + std::pow(ay * size[1], 2) + std::pow(az * size[2], 2));
        break;
      case mjGEOM_BOX:
        extent = ax * size[0] + ay * size[1] + az * size[2];
        break;
      default:
        extent = m->geom_rbound[g];
        break;
    }
    lo = std::min(lo, d->geom_xpos[3 * g + 2] - extent);
    hi = std::max(hi, d->geom_xpos[3 * g + 2] + extent);
  }
  return {lo, hi};
}

void World::set_object_pose(int index, const Vec3& pos, const std::array<double, 4>& quat) {
  DOJO_CHECK(index >= 0 && index < num_objects(),
             "World: object index " + std::to_string(index) + " out of range");
  mjData* d = data_;
  const int q = object_qpos_[index];
  const int v = object_dof_[index];
  for (int k = 0; k < 3; ++k) d->qpos[q + k] = pos[k];
  double n = std::sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
  for (int k = 0; k < 4; ++k) d->qpos[q + 3 + k] = quat[k] / n;
  for (int k = 0; k < 6; ++k) d->qvel[v + k] = 0;
  mj_forward(model_, data_);
}

bool World::touching(int index) const {
  const mjModel* m = model_;
  const mjData* d = data_;
  const int body = object_body_[index];
  for (int c = 0; c < d->ncon; ++c) {
    const int g1 = d->contact[c].geom1, g2 = d->contact[c].geom2;
    int other = -1;
    if (m->geom_bodyid[g1] == body) other = g2;
    if (m->geom_bodyid[g2] == body) other = g1;
    if (other >= 0 &&
        std::find(effector_geoms_.begin(), effector_geoms_.end(), other) != effector_geoms_.end()) {
      return true;
    }
  }
  return false;
}

double World::sim_time() const { return data_->time; }

}  // namespace dojo::sim
