// The embodiment table: which robots the engine reads from LeRobot datasets and where each one's
// actions sit in the 384-d unified action vector. The released robots (gr1, g1, yam, agibot) are
// built in; a user adds their own robot with a JSON file, without recompiling:
//
//   dojo --embodiments my_robots.json wm train ...      (or DOJO_EMBODIMENTS=my_robots.json)
//
//   {"embodiments": [{
//      "name": "so100",                     // --embodiment so100; also the action slot's name
//      "robot_types": ["so100", "so-100"],  // info.json robot_type values naming it (any case)
//      "slot": [220, 226],                  // its columns [begin, end) of the 384-d vector
//      "action": [["arm", 5], ["gripper", 1]],  // modality.json action keys, in slot order
//      "camera": "front",                   // modality.json video key read by default (optional)
//      "frame_stride": 1,                   // recorded frames per model frame (optional, 1)
//      "teleop": [{"name": "arm_0", "rate": 0.5, "keys": ["KeyA", "KeyD"]}, ...]}]}
//                                           // the teleoperation page's controls (optional)
//
// A new robot's slot may take columns of the human ranges (gr1_retargeted [29, 58), mano
// [220, 352)), which no robot dataset fills, but never a robot's, the latent actions' or another
// user robot's: a released model's columns for GR-1 keep meaning GR-1. `dojo data embodiments`
// prints the whole table in this format.
#pragma once

#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

#include "data/actions.h"
#include "data/lerobot.h"

namespace dojo::data {

struct EmbodimentSpec {
  std::string name;
  std::vector<std::string> robot_types;  // lower-cased; the name itself when the file gives none
  int slot_begin = 0, slot_end = 0;
  std::vector<std::pair<std::string, int>> action;  // modality action keys and widths, slot order
  std::string camera;
  int frame_stride = 1;
  // The teleoperation page's controls, one per action dimension in slot order, as in the built-in
  // robots' mapping files (src/serve/pages/*.mapping.json): name, rate (the robot's units per
  // second at full deflection), keys [negative, positive], gamepad_axis, gamepad_buttons, mouse.
  // Empty: teleop_mapping() makes one.
  nlohmann::json teleop = nlohmann::json::array();

  nlohmann::json to_json() const;
  // Throws dojo::Error "WHERE: embodiments[i].FIELD: ..." for a missing or malformed field.
  static EmbodimentSpec from_json(const nlohmann::json& j, const std::string& where);
};

// Checks `spec` against the table (name and slot free, widths filling the slot) and adds it: its
// slot to all_slots(), its layout to robot_layouts(). Adding the same spec again does nothing.
// Register at start-up, before any thread reads the tables. Throws dojo::Error naming `where`.
void register_embodiment(const EmbodimentSpec& spec, const std::string& where);
// Reads {"embodiments": [...]} from `file` and registers each entry.
void load_embodiment_table(const std::filesystem::path& file);

// The robots registered from tables, in order.
std::vector<EmbodimentSpec> user_embodiments();
const EmbodimentSpec* find_user_embodiment(const std::string& name);  // nullptr when none
// The name of the user robot whose robot_types hold `robot_type` (any case); "" when none.
std::string user_robot_for(const std::string& robot_type);
// "gr1, g1, yam, agibot" and the user's robots: for error messages.
std::string embodiment_names();
// Every robot, built-in and user, as {"embodiments": [...]} in the file's format.
nlohmann::json embodiment_table();
// The teleoperation page's mapping file for a user robot: its "teleop" entries, else one control
// per dimension on the key pairs A/D, S/W, F/R, G/T, Q/E, C/O, Z/X, V/B, N/M, J/L, U/I at 1 unit/s.
nlohmann::json teleop_mapping(const EmbodimentSpec& spec);

// Registration hooks of the tables, defined beside them (actions.cpp, lerobot.cpp).
void add_action_slot(const std::string& name, int begin, int end);
void add_robot_layout(RobotLayout layout);

}  // namespace dojo::data
