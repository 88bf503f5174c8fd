#include "data/embodiments.h"

#include <algorithm>
#include <cctype>
#include <deque>
#include <map>

#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "core/text.h"
#include "data/episode_clip.h"

namespace dojo::data {
namespace {

// Slots a new robot may share: the human ranges, which no robot dataset fills.
bool shareable(const std::string& slot) { return slot == "gr1_retargeted" || slot == "mano"; }

const std::vector<std::string>& reserved_names() {
  static const std::vector<std::string> names = {"auto", "human", "none"};
  return names;
}

std::deque<EmbodimentSpec>& registry() {  // a deque: find_user_embodiment's pointers stay valid
  static std::deque<EmbodimentSpec> specs;
  return specs;
}

bool valid_name(const std::string& name) {
  return !name.empty() && std::all_of(name.begin(), name.end(), [](unsigned char c) {
    return std::islower(c) || std::isdigit(c) || c == '_' || c == '-';
  });
}

template <typename T>
T field(const nlohmann::json& j, const char* key, const std::string& where, const char* expected) {
  try {
    return j.at(key).get<T>();
  } catch (const nlohmann::json::exception&) {
    throw Error(where + "." + key + ": " + (j.contains(key) ? "must be " : "missing; needs ") + expected);
  }
}

Modality default_modality(const EmbodimentSpec& spec) {
  Modality m;
  int at = 0;
  for (const auto& [key, width] : spec.action) m.action.push_back({key, at, at + width, ""}), at += width;
  if (!spec.camera.empty()) m.video[spec.camera] = "observation.images." + spec.camera;
  return m;
}

bool same(const EmbodimentSpec& a, const EmbodimentSpec& b) { return a.to_json() == b.to_json(); }

}  // namespace

nlohmann::json EmbodimentSpec::to_json() const {
  nlohmann::json actions = nlohmann::json::array();
  for (const auto& [key, width] : action) actions.push_back({key, width});
  return {{"name", name},      {"robot_types", robot_types}, {"slot", {slot_begin, slot_end}},
          {"action", actions}, {"camera", camera},           {"frame_stride", frame_stride}};
}

EmbodimentSpec EmbodimentSpec::from_json(const nlohmann::json& j, const std::string& where) {
  if (!j.is_object()) throw Error(where + ": must be an object");
  EmbodimentSpec s;
  s.name = field<std::string>(j, "name", where, "a string");
  if (!valid_name(s.name))
    throw Error(where + ".name: '" + s.name + "' must be lower-case letters, digits, '_' or '-'");
  const std::string at = where + " (" + s.name + ")";
  if (j.contains("robot_types"))
    for (const auto& t : field<std::vector<std::string>>(j, "robot_types", at, "a list of strings"))
      s.robot_types.push_back(ascii_lower(t));
  if (s.robot_types.empty()) s.robot_types = {s.name};
  const auto slot = field<std::vector<int>>(j, "slot", at, "[begin, end] of the 384-d action vector");
  if (slot.size() != 2) throw Error(at + ".slot: needs [begin, end] of the 384-d action vector");
  s.slot_begin = slot[0];
  s.slot_end = slot[1];
  const auto actions = field<nlohmann::json>(j, "action", at, "a list of [key, width]");
  if (!actions.is_array() || actions.empty())
    throw Error(at + ".action: needs a non-empty list of [key, width]");
  for (const auto& a : actions) {
    if (!a.is_array() || a.size() != 2 || !a[0].is_string() || !a[1].is_number_integer() ||
        a[1].get<int>() <= 0)
      throw Error(at + ".action: each entry must be [key, width > 0], got " + a.dump());
    s.action.push_back({a[0].get<std::string>(), a[1].get<int>()});
  }
  if (j.contains("camera")) s.camera = field<std::string>(j, "camera", at, "a string");
  if (j.contains("frame_stride")) {
    s.frame_stride = field<int>(j, "frame_stride", at, "an integer >= 1");
    if (s.frame_stride < 1) throw Error(at + ".frame_stride: must be >= 1");
  }
  if (j.contains("teleop")) {
    s.teleop = j.at("teleop");
    if (!s.teleop.is_array()) throw Error(at + ".teleop: must be a list of controls");
    for (const auto& control : s.teleop)
      if (!control.is_object() || !control.contains("rate") || !control.at("rate").is_number())
        throw Error(at + ".teleop: each control must be an object with a numeric 'rate', got " +
                    control.dump());
  }
  return s;
}

void register_embodiment(const EmbodimentSpec& spec, const std::string& where) {
  const std::string at = where + " (" + spec.name + ")";
  if (const auto* known = find_user_embodiment(spec.name)) {
    if (same(*known, spec)) return;
    throw Error(at + ": another robot of that name is registered already, with other fields");
  }
  if (std::find(reserved_names().begin(), reserved_names().end(), spec.name) != reserved_names().end() ||
      find_robot_layout(spec.name) != nullptr)
    throw Error(at + ".name: '" + spec.name + "' is a built-in embodiment; choose another name");
  for (const auto& slot : all_slots())
    if (spec.name == slot.name) throw Error(at + ".name: '" + spec.name + "' names a built-in action slot");
  const int latent_begin = slots::kLatent.begin;
  if (spec.slot_begin < 0 || spec.slot_end <= spec.slot_begin || spec.slot_end > latent_begin)
    throw Error(at + ".slot: [" + std::to_string(spec.slot_begin) + ", " + std::to_string(spec.slot_end) +
                ") must lie in [0, " + std::to_string(latent_begin) +
                ") (the latent actions own the columns after it)");
  for (const auto& slot : all_slots()) {
    const bool overlaps = spec.slot_begin < slot.end && slot.begin < spec.slot_end;
    if (overlaps && !shareable(slot.name))
      throw Error(at + ".slot: [" + std::to_string(spec.slot_begin) + ", " + std::to_string(spec.slot_end) +
                  ") overlaps '" + slot.name + "' [" + std::to_string(slot.begin) + ", " +
                  std::to_string(slot.end) +
                  "); a new robot may take columns of gr1_retargeted [29, 58) or "
                  "mano [220, 352) only");
  }
  int width = 0;
  for (const auto& [key, w] : spec.action) width += w;
  if (width != spec.slot_end - spec.slot_begin)
    throw Error(at + ".action: the keys' widths add up to " + std::to_string(width) + ", the slot holds " +
                std::to_string(spec.slot_end - spec.slot_begin));
  for (const auto& t : spec.robot_types) {
    const auto owner = user_robot_for(t);
    if (!owner.empty()) throw Error(at + ".robot_types: '" + t + "' already names " + owner);
  }
  add_action_slot(spec.name, spec.slot_begin, spec.slot_end);
  const ActionSlot slot = slot_by_name(spec.name);
  add_robot_layout({spec.name, slot, spec.camera, spec.action, default_modality(spec)});
  registry().push_back(spec);
  LOG_DEBUG("embodiment ", spec.name, " registered from ", where, ": slot [", spec.slot_begin, ", ",
            spec.slot_end, ")");
}

void load_embodiment_table(const std::filesystem::path& file) {
  const auto j = read_json_file(file);
  const std::string where = file.string();
  if (!j.is_object() || !j.contains("embodiments") || !j.at("embodiments").is_array())
    throw Error(where + ": needs {\"embodiments\": [...]}");
  const auto& list = j.at("embodiments");
  for (size_t i = 0; i < list.size(); ++i) {
    const std::string at = where + ": embodiments[" + std::to_string(i) + "]";
    register_embodiment(EmbodimentSpec::from_json(list[i], at), at);
  }
}

std::vector<EmbodimentSpec> user_embodiments() { return {registry().begin(), registry().end()}; }

const EmbodimentSpec* find_user_embodiment(const std::string& name) {
  for (const auto& s : registry())
    if (s.name == name) return &s;
  return nullptr;
}

std::string user_robot_for(const std::string& robot_type) {
  const auto type = ascii_lower(robot_type);
  for (const auto& s : registry())
    if (std::find(s.robot_types.begin(), s.robot_types.end(), type) != s.robot_types.end()) return s.name;
  return "";
}

std::string embodiment_names() {
  std::string names;
  for (const auto& layout : robot_layouts()) names += (names.empty() ? "" : ", ") + layout.name;
  return names;
}

nlohmann::json embodiment_table() {
  // The built-in robots' detection words are substrings of robot_type (lerobot.h, detect_robot).
  const std::map<std::string, std::vector<std::string>> builtin_types = {
      {"gr1", {"gr1", "gr-1", "fourier"}}, {"g1", {"g1"}}, {"yam", {"yam"}}, {"agibot", {"agibot"}}};
  auto list = nlohmann::json::array();
  for (const auto& layout : robot_layouts()) {
    if (const auto* user = find_user_embodiment(layout.name)) {
      list.push_back(user->to_json());
      continue;
    }
    EmbodimentSpec s;
    s.name = layout.name;
    s.robot_types =
        builtin_types.count(layout.name) ? builtin_types.at(layout.name) : std::vector<std::string>{};
    s.slot_begin = layout.slot.begin;
    s.slot_end = layout.slot.end;
    s.action = layout.action_order;
    s.camera = layout.camera;
    s.frame_stride = released_frame_stride(layout.name);
    auto j = s.to_json();
    j["built_in"] = true;
    list.push_back(j);
  }
  return {{"embodiments", list}};
}

nlohmann::json teleop_mapping(const EmbodimentSpec& spec) {
  nlohmann::json dims = spec.teleop;
  if (dims.empty()) {
    static const std::vector<std::pair<const char*, const char*>> pairs = {
        {"KeyA", "KeyD"}, {"KeyS", "KeyW"}, {"KeyF", "KeyR"}, {"KeyG", "KeyT"},
        {"KeyQ", "KeyE"}, {"KeyC", "KeyO"}, {"KeyZ", "KeyX"}, {"KeyV", "KeyB"},
        {"KeyN", "KeyM"}, {"KeyJ", "KeyL"}, {"KeyU", "KeyI"}};
    size_t d = 0;
    for (const auto& [key, width] : spec.action)
      for (int k = 0; k < width; ++k, ++d) {
        nlohmann::json control = {{"name", width == 1 ? key : key + "." + std::to_string(k)}, {"rate", 1.0}};
        if (d < pairs.size()) control["keys"] = {pairs[d].first, pairs[d].second};
        dims.push_back(control);
      }
  }
  return {{"embodiment", spec.name},
          {"about", spec.name + " (embodiment table): rates in the robot's own units per second"},
          {"dims", dims}};
}

}  // namespace dojo::data
