// Human skills for DojoSim: the HumanController, which plans keyframe scripts for the hand
// (push, poke, pat, sweep, pick-and-place, stack, topple, reach, lift-and-drop) from the object
// poses when each skill starts, and the human-skill names.
#include "sim/skills.h"

#include <algorithm>
#include <array>
#include <cmath>

#include "core/error.h"
#include "sim/rng.h"
#include "sim/skill_script.h"

namespace dojo::sim {
namespace {

constexpr double kPalmHalf = 0.011;    // palm half-thickness
constexpr double kFingerReach = 0.12;  // palm centre -> fingertips (flat hand)

class HumanController : public Controller {
 public:
  HumanController(const World& world, const HumanSkillOptions& options, uint64_t seed)
      : options_(options), rng_(seed) {
    if (options_.skills.empty()) options_.skills = all_human_skills();
    rest_ = world.initial_command();
    speed_ = rng_.uniform(0.75, 1.35);
    log_ = nlohmann::json::array();
  }

  std::vector<double> act(const World& world, int step) override {
    const double dt = world.control_dt();
    const double now = step * dt;
    if (!script_.started()) {
      script_.start(world.last_command(), now);
      plan(world, now);
    } else if (script_.done(now) && options_.chain) {
      script_.start(script_.end(), now);
      plan(world, now);
    }
    return script_.eval(now + dt);
  }

  std::string task_text() const override {
    std::string text;
    for (size_t i = 0; i < texts_.size(); ++i) text += (i ? ", then " : "") + texts_[i];
    return text;
  }

  nlohmann::json describe() const override {
    return {{"controller", "human_skill"}, {"speed", speed_}, {"skills", log_}};
  }

 private:
  // -- helpers ----------------------------------------------------------------------------------
  static Pose pose(double x, double y, double z, double yaw, double pitch, double curl) {
    return {x, y, z, yaw, pitch, curl};
  }
  // Unit vector along the fingers for a hand yaw.
  static std::array<double, 2> along(double yaw) { return {-std::sin(yaw), std::cos(yaw)}; }
  static double yaw_toward(double dx, double dy) { return std::atan2(-dx, dy); }

  // Moves to `target` with a duration from the distance and the episode's speed.
  void move(const Pose& target, double base_speed = 0.35) {
    const Pose& from = script_.end();
    const double dist = std::sqrt(std::pow(target[0] - from[0], 2) + std::pow(target[1] - from[1], 2) +
                                  std::pow(target[2] - from[2], 2)) +
                        0.05 * std::fabs(target[3] - from[3]) + 0.03 * std::fabs(target[4] - from[4]);
    const double duration = std::clamp(dist / (base_speed * speed_), 0.3, 1.8) * rng_.uniform(0.9, 1.1);
    script_.add(target, duration);
  }
  void timed(const Pose& target, double seconds) { script_.add(target, seconds / speed_); }
  Pose with(const Pose& p, int i, double v) {
    Pose q = p;
    q[i] = v;
    return q;
  }
  void retreat() {
    Pose r = rest_;
    r[0] += rng_.uniform(-0.05, 0.05);
    r[1] += rng_.uniform(-0.03, 0.03);
    r[2] += rng_.uniform(-0.02, 0.03);
    r[3] += rng_.uniform(-0.2, 0.2);
    r[4] = 0.0;
    r[5] = rng_.uniform(0.15, 0.4);
    Pose up = script_.end();
    up[2] = std::max(up[2], r[2]);
    move(up);
    move(r);
    script_.wait(rng_.uniform(0.0, 0.4));
  }

  // Free table spot for placing an object of footprint radius r, 8-20 cm from `from`.
  bool free_spot(const World& w, const ObjInfo& o, double* x, double* y) {
    for (int attempt = 0; attempt < 60; ++attempt) {
      const double a = rng_.uniform(-M_PI, M_PI), d = rng_.uniform(0.08, 0.2);
      const double cx = o.pos[0] + d * std::cos(a), cy = o.pos[1] + d * std::sin(a);
      if (cx < -0.22 || cx > 0.22 || cy < -0.1 || cy > 0.2) continue;
      bool ok = true;
      for (int j = 0; j < w.num_objects() && ok; ++j) {
        if (j == o.index) continue;
        const ObjInfo other = object_info(w, j);
        if (std::hypot(cx - other.pos[0], cy - other.pos[1]) < o.radius + other.radius + 0.02) ok = false;
      }
      const BinSpec& b = w.spec().bin;
      if (b.enabled && std::fabs(cx - b.center[0]) < b.half_x + o.radius + 0.03 &&
          std::fabs(cy - b.center[1]) < b.half_y + o.radius + 0.03) {
        ok = false;
      }
      if (ok) {
        *x = cx;
        *y = cy;
        return true;
      }
    }
    return false;
  }

  // -- planning ---------------------------------------------------------------------------------
  void plan(const World& w, double now) {
    HumanSkill skill = rng_.pick(options_.skills);
    const int n = w.num_objects();
    int target = -1;
    if (n > 0)
      target = (log_.empty() && options_.target_object >= 0 && options_.target_object < n)
                   ? options_.target_object
                   : rng_.randint(0, n - 1);
    if (n == 0) skill = HumanSkill::kReach;
    if (skill == HumanSkill::kStack && n < 2) skill = HumanSkill::kPickPlace;
    std::string text;
    nlohmann::json params;
    switch (skill) {
      case HumanSkill::kPush:
        text = plan_push(object_info(w, target), &params);
        break;
      case HumanSkill::kPoke:
        text = plan_poke(object_info(w, target), &params);
        break;
      case HumanSkill::kPat:
        text = plan_pat(object_info(w, target), &params);
        break;
      case HumanSkill::kSweep:
        text = plan_sweep(object_info(w, target), &params);
        break;
      case HumanSkill::kPickPlace:
        text = plan_pick_place(w, object_info(w, target), &params);
        break;
      case HumanSkill::kStack: {
        // Stack onto an object with a flat top, other than the one carried.
        std::vector<int> bases;
        for (int j = 0; j < n; ++j) {
          const Shape s = w.spec().objects[j].shape;
          if (j != target &&
              (s == Shape::kBox || s == Shape::kCylinder || s == Shape::kPlate || s == Shape::kMug)) {
            bases.push_back(j);
          }
        }
        if (bases.empty()) {
          skill = HumanSkill::kPickPlace;
          text = plan_pick_place(w, object_info(w, target), &params);
        } else {
          const int base = rng_.pick(bases);
          text = plan_stack(w, object_info(w, target), object_info(w, base), &params);
        }
        break;
      }
      case HumanSkill::kTopple: {
        std::vector<int> tall;
        for (int j = 0; j < n; ++j) {
          const ObjInfo o = object_info(w, j);
          if (o.top - o.bottom > std::max(0.06, 1.2 * o.radius * 2)) tall.push_back(j);
        }
        if (!tall.empty()) {
          if (std::find(tall.begin(), tall.end(), target) == tall.end()) target = rng_.pick(tall);
          text = plan_topple(object_info(w, target), &params);
        } else {
          skill = HumanSkill::kPush;
          text = plan_push(object_info(w, target), &params);
        }
        break;
      }
      case HumanSkill::kReach:
        text = n > 0 ? plan_reach(object_info(w, target), &params) : plan_wave(&params);
        break;
      case HumanSkill::kLiftDrop:
        text = plan_lift_drop(w, object_info(w, target), &params);
        break;
    }
    texts_.push_back(text);
    log_.push_back({{"skill", to_string(skill)},
                    {"object", target},
                    {"text", text},
                    {"start_step", static_cast<int>(std::lround(now / w.control_dt()))},
                    {"params", params}});
  }

  // How far the hand's outline reaches from the palm centre in horizontal direction (dx, dy)
  // for a hand yaw: the palm plus fingers, roughly a 9 x 17 cm rectangle.
  static double hand_extent(double yaw, double dx, double dy) {
    const auto u = along(yaw);
    const double a = u[0] * dx + u[1] * dy;  // along the fingers
    const double c = u[1] * dx - u[0] * dy;  // across (toward the pinky, +x at yaw 0)
    return (a > 0 ? a * kFingerReach : -a * 0.045) + std::fabs(c) * 0.045;
  }

  // Pushes with whichever side of the hand faces the motion: fingertips when pushing away, the
  // pinky edge when pushing right, the thumb side when pushing left. The hand keeps a natural
  // right-hand yaw, so the arm never twists back over itself.
  std::string plan_push(const ObjInfo& o, nlohmann::json* params) {
    const double phi = rng_.uniform(0.0, 180.0) * M_PI / 180.0;
    const double dx = std::cos(phi), dy = std::sin(phi);
    const double yaw = std::clamp(yaw_toward(dx, dy), -1.0, 0.8) + rng_.uniform(-0.15, 0.15);
    const double curl = rng_.uniform(0.05, 0.2);
    // Low enough to catch flat objects (plates, rings) with the palm's edge.
    const double z = std::max(0.014, o.bottom + std::clamp(0.5 * (o.top - o.bottom), 0.005, 0.035));
    const double back = o.radius + 0.02 + hand_extent(yaw, dx, dy);
    const double sx = o.pos[0] - dx * back, sy = o.pos[1] - dy * back;
    double dist = rng_.uniform(0.06, 0.14);
    while (dist > 0.02 && !on_table(o.pos[0] + dx * dist, o.pos[1] + dy * dist)) dist -= 0.01;
    const double travel = dist + 0.02;
    move(pose(sx, sy, z + 0.07, yaw, 0.0, curl));
    timed(pose(sx, sy, z, yaw, 0.0, curl), 0.4);
    script_.add(pose(sx + dx * travel, sy + dy * travel, z, yaw, 0.0, curl), travel / (0.12 * speed_));
    timed(pose(sx + dx * travel, sy + dy * travel, z + 0.07, yaw, 0.0, curl), 0.4);
    retreat();
    *params = {{"direction_deg", phi * 180 / M_PI}, {"distance", dist}, {"yaw", yaw}};
    return "push the " + o.name + " " + direction_words(dx, dy);
  }

  std::string plan_poke(const ObjInfo& o, nlohmann::json* params) {
    const double phi = rng_.uniform(40.0, 140.0) * M_PI / 180.0;
    const double dx = std::cos(phi), dy = std::sin(phi);
    const double yaw = yaw_toward(dx, dy);
    const double pitch = rng_.uniform(0.55, 0.8), curl = rng_.uniform(0.0, 0.1);
    const double reach = kFingerReach * std::cos(pitch), drop = kFingerReach * std::sin(pitch);
    const double contact = std::max(0.009, o.bottom + std::min(0.6 * (o.top - o.bottom), 0.04));
    // Fingertip positions: pulled back, and pressed 1.2 cm into the object's side.
    const double side = std::max(0.6 * o.radius, 0.012);
    const double bx = o.pos[0] - dx * (side + 0.045), by = o.pos[1] - dy * (side + 0.045);
    const double ix = o.pos[0] - dx * (side - 0.012), iy = o.pos[1] - dy * (side - 0.012);
    const double z = contact + drop;
    auto palm = [&](double tx, double ty, double tz) {
      return pose(tx - dx * reach, ty - dy * reach, tz, yaw, pitch, curl);
    };
    move(palm(bx, by, z + 0.06));
    timed(palm(bx, by, z), 0.35);
    const int jabs = rng_.randint(1, 3);
    for (int k = 0; k < jabs; ++k) {
      timed(palm(ix, iy, z), rng_.uniform(0.2, 0.3));
      timed(palm(bx, by, z), rng_.uniform(0.25, 0.35));
    }
    timed(palm(bx, by, z + 0.06), 0.35);
    retreat();
    *params = {{"direction_deg", phi * 180 / M_PI}, {"jabs", jabs}, {"pitch", pitch}};
    return "poke the " + o.name;
  }

  std::string plan_pat(const ObjInfo& o, nlohmann::json* params) {
    const double yaw = rng_.uniform(-0.3, 0.5), curl = rng_.uniform(0.0, 0.15);
    const auto u = along(yaw);
    const double cx = o.pos[0] - u[0] * 0.03, cy = o.pos[1] - u[1] * 0.03;
    const double up = o.top + kPalmHalf + rng_.uniform(0.04, 0.07), down = o.top + kPalmHalf - 0.004;
    move(pose(cx, cy, up, yaw, 0.0, curl));
    const int pats = rng_.randint(2, 4);
    for (int k = 0; k < pats; ++k) {
      timed(pose(cx, cy, down, yaw, 0.0, curl), rng_.uniform(0.15, 0.25));
      timed(pose(cx, cy, up, yaw, 0.0, curl), rng_.uniform(0.2, 0.3));
    }
    retreat();
    *params = {{"pats", pats}, {"height", up - down}};
    return "pat the " + o.name;
  }

  std::string plan_sweep(const ObjInfo& o, nlohmann::json* params) {
    double side = rng_.bernoulli(0.5) ? 1.0 : -1.0;
    if (o.pos[0] > 0.15) side = -1.0;
    if (o.pos[0] < -0.15) side = 1.0;
    const double yaw = rng_.uniform(-0.2, 0.3), curl = rng_.uniform(0.1, 0.3);
    const double y = o.pos[1] - rng_.uniform(0.0, 0.07);
    const double z = 0.015;
    const double x0 = o.pos[0] - side * (o.radius + 0.07), x1 = o.pos[0] + side * rng_.uniform(0.08, 0.16);
    move(pose(x0, y, 0.08, yaw, 0.05, curl));
    timed(pose(x0, y, z, yaw, 0.05, curl), 0.35);
    script_.add(pose(x1, y, z, yaw, 0.05, curl), std::fabs(x1 - x0) / (0.2 * speed_));
    timed(pose(x1, y, 0.08, yaw, 0.05, curl), 0.35);
    retreat();
    *params = {{"side", side}, {"distance", std::fabs(x1 - x0)}};
    return "sweep the " + o.name + (side > 0 ? " to the right" : " to the left");
  }

  // Grasp: the object ends up under the front of the palm with the fingers curled around it.
  struct Grasp {
    double x, y, z, yaw, ux, uy;
  };
  // Clearance between the flat hand's outline (palm + fingers) at (x, y, yaw) and every object
  // other than `target`; negative when the hand would land on one of them.
  static double hand_clearance(const World& w, int target, double x, double y, double yaw) {
    const auto u = along(yaw);
    double clearance = 1.0;
    for (int j = 0; j < w.num_objects(); ++j) {
      if (j == target) continue;
      const ObjInfo other = object_info(w, j);
      const double dx = other.pos[0] - x, dy = other.pos[1] - y;
      const double a = dx * u[0] + dy * u[1], c = dx * u[1] - dy * u[0];
      const double da = std::max({-0.05 - a, a - (kFingerReach + 0.01), 0.0}),
                   dc = std::max(std::fabs(c) - 0.05, 0.0);
      clearance = std::min(clearance, std::hypot(da, dc) - other.radius);
    }
    return clearance;
  }

  Grasp plan_grasp(const World& w, const ObjInfo& o) {
    Grasp g;
    // A natural yaw whose fingers do not land on a neighbouring object.
    double best = -1e9;
    for (int k = 0; k < 8; ++k) {
      const double yaw = rng_.uniform(-0.5, 0.7);
      const auto v = along(yaw);
      const double clearance =
          hand_clearance(w, o.index, o.pos[0] - v[0] * 0.012, o.pos[1] - v[1] * 0.012, yaw);
      const double score = std::min(clearance, 0.02) - 0.01 * std::fabs(yaw - 0.1);
      if (score > best) {
        best = score;
        g.yaw = yaw;
      }
    }
    const auto u = along(g.yaw);
    g.ux = u[0];
    g.uy = u[1];
    g.x = o.pos[0] - u[0] * 0.012;
    g.y = o.pos[1] - u[1] * 0.012;
    g.z = o.top + kPalmHalf - 0.002;  // palm presses lightly on the top
    move(pose(g.x, g.y, g.z + 0.06, g.yaw, 0.0, 0.05));
    timed(pose(g.x, g.y, g.z, g.yaw, 0.0, 0.05), 0.4);
    timed(pose(g.x, g.y, g.z, g.yaw, 0.0, 0.95), 0.45);
    script_.wait(0.15);
    return g;
  }

  // Carries the grasped object so its centre ends above (tx, ty) with its bottom `clearance`
  // above `surface`, then lets go.
  void place(const ObjInfo& o, const Grasp& g, double tx, double ty, double surface, double lift) {
    const double carry = g.z + lift;
    timed(pose(g.x, g.y, carry, g.yaw, 0.0, 0.95), 0.5);
    const double px = tx - g.ux * 0.012, py = ty - g.uy * 0.012;
    move(pose(px, py, carry, g.yaw, 0.0, 0.95), 0.3);
    const double z = g.z + (surface - o.bottom) + 0.006;
    timed(pose(px, py, z, g.yaw, 0.0, 0.95), 0.5);
    timed(pose(px, py, z, g.yaw, 0.0, 0.1), 0.35);
    timed(pose(px, py, z + 0.06, g.yaw, 0.0, 0.1), 0.35);
    retreat();
  }

  std::string plan_pick_place(const World& w, const ObjInfo& o, nlohmann::json* params) {
    const BinSpec& bin = w.spec().bin;
    double tx = 0, ty = 0, surface = 0.0;
    std::string text;
    if (bin.enabled && rng_.bernoulli(0.5)) {
      tx = bin.center[0] + rng_.uniform(-0.03, 0.03);
      ty = bin.center[1] + rng_.uniform(-0.03, 0.03);
      surface = 0.004;
      text = "put the " + o.name + " in the tray";
    } else if (free_spot(w, o, &tx, &ty)) {
      text = "pick up the " + o.name + " and move it " + direction_words(tx - o.pos[0], ty - o.pos[1]);
    } else {
      tx = o.pos[0];
      ty = o.pos[1];
      text = "pick up the " + o.name + " and put it back down";
    }
    const Grasp g = plan_grasp(w, o);
    place(o, g, tx, ty, surface, rng_.uniform(0.08, 0.12));
    *params = {{"target", {tx, ty}}};
    return text;
  }

  std::string plan_stack(const World& w, const ObjInfo& o, const ObjInfo& base, nlohmann::json* params) {
    const Grasp g = plan_grasp(w, o);
    const double lift = std::max(rng_.uniform(0.08, 0.12), base.top - o.bottom + 0.05);
    place(o, g, base.pos[0], base.pos[1], base.top, lift);
    *params = {{"base", base.index}};
    return "stack the " + o.name + " on the " + base.name;
  }

  std::string plan_topple(const ObjInfo& o, nlohmann::json* params) {
    const double phi = rng_.uniform(0.0, 180.0) * M_PI / 180.0;
    const double dx = std::cos(phi), dy = std::sin(phi);
    const double yaw = std::clamp(yaw_toward(dx, dy), -1.0, 0.8);
    const double curl = rng_.uniform(0.1, 0.25);
    const double z = o.bottom + rng_.uniform(0.7, 0.85) * (o.top - o.bottom);
    const double back = o.radius + 0.025 + hand_extent(yaw, dx, dy);
    const double sx = o.pos[0] - dx * back, sy = o.pos[1] - dy * back;
    const double travel = 0.03 + rng_.uniform(0.07, 0.1);
    move(pose(sx, sy, z + 0.06, yaw, 0.0, curl));
    timed(pose(sx, sy, z, yaw, 0.0, curl), 0.35);
    script_.add(pose(sx + dx * travel, sy + dy * travel, z, yaw, 0.0, curl), travel / (0.3 * speed_));
    timed(pose(sx + dx * travel, sy + dy * travel, z + 0.06, yaw, 0.0, curl), 0.35);
    retreat();
    *params = {{"direction_deg", phi * 180 / M_PI}, {"height", z}};
    return "knock over the " + o.name;
  }

  std::string plan_reach(const ObjInfo& o, nlohmann::json* params) {
    const double yaw = rng_.uniform(-0.3, 0.5), pitch = rng_.uniform(0.0, 0.4), curl = rng_.uniform(0.1, 0.5);
    const auto u = along(yaw);
    const double hx = o.pos[0] - u[0] * 0.05, hy = o.pos[1] - u[1] * 0.05;
    const double z = o.top + kPalmHalf + rng_.uniform(0.05, 0.1);
    move(pose(hx, hy, z, yaw, pitch, curl));
    const bool wave = rng_.bernoulli(0.5);
    if (wave) {
      for (int k = 0; k < 2; ++k) {
        timed(pose(hx, hy, z, yaw + 0.35, pitch, curl), 0.3);
        timed(pose(hx, hy, z, yaw - 0.35, pitch, curl), 0.3);
      }
      timed(pose(hx, hy, z, yaw, pitch, curl), 0.2);
    }
    script_.wait(rng_.uniform(0.2, 0.7));
    retreat();
    *params = {{"wave", wave}, {"height", z}};
    return (wave ? "wave over the " : "reach toward the ") + o.name;
  }

  std::string plan_wave(nlohmann::json* params) {
    const double x = rng_.uniform(-0.15, 0.15), y = rng_.uniform(-0.05, 0.15), z = rng_.uniform(0.08, 0.15);
    const double yaw = rng_.uniform(-0.3, 0.5);
    move(pose(x, y, z, yaw, 0.0, 0.1));
    for (int k = 0; k < 2; ++k) {
      timed(pose(x, y, z, yaw + 0.35, 0.0, 0.1), 0.3);
      timed(pose(x, y, z, yaw - 0.35, 0.0, 0.1), 0.3);
    }
    retreat();
    *params = {{"at", {x, y, z}}};
    return "wave over the table";
  }

  std::string plan_lift_drop(const World& w, const ObjInfo& o, nlohmann::json* params) {
    const Grasp g = plan_grasp(w, o);
    const double lift = rng_.uniform(0.1, 0.16);
    timed(pose(g.x, g.y, g.z + lift, g.yaw, 0.0, 0.95), 0.6);
    script_.wait(rng_.uniform(0.1, 0.4));
    timed(pose(g.x, g.y, g.z + lift, g.yaw, 0.0, 0.1), 0.2);
    script_.wait(0.3);
    retreat();
    *params = {{"lift", lift}};
    return "lift the " + o.name + " and drop it";
  }

  HumanSkillOptions options_;
  Rng rng_;
  Pose rest_;
  double speed_;
  Script script_;
  std::vector<std::string> texts_;
  nlohmann::json log_;
};

}  // namespace

// ================================================================================================

const char* to_string(HumanSkill skill) {
  switch (skill) {
    case HumanSkill::kPush:
      return "push";
    case HumanSkill::kPoke:
      return "poke";
    case HumanSkill::kPat:
      return "pat";
    case HumanSkill::kSweep:
      return "sweep";
    case HumanSkill::kPickPlace:
      return "pick_place";
    case HumanSkill::kStack:
      return "stack";
    case HumanSkill::kTopple:
      return "topple";
    case HumanSkill::kReach:
      return "reach";
    case HumanSkill::kLiftDrop:
      return "lift_drop";
  }
  return "?";
}

HumanSkill parse_human_skill(const std::string& name) {
  for (HumanSkill s : all_human_skills()) {
    if (name == to_string(s)) return s;
  }
  throw UsageError("unknown human skill '" + name +
                   "' (expected push, poke, pat, sweep, pick_place, stack, topple, reach or lift_drop)");
}

std::vector<HumanSkill> all_human_skills() {
  std::vector<HumanSkill> out;
  for (int i = 0; i < kNumHumanSkills; ++i) out.push_back(static_cast<HumanSkill>(i));
  return out;
}

std::unique_ptr<Controller> make_human_controller(const World& world, const HumanSkillOptions& options,
                                                  uint64_t seed) {
  DOJO_CHECK(world.embodiment() == Embodiment::kHuman, "human skills need a human scene");
  return std::make_unique<HumanController>(world, options, seed);
}

}  // namespace dojo::sim
