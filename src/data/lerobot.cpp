// LeRobot datasets (see lerobot.h): the robot layouts, modality.json, robot detection, path
// templates and the dataset's read functions (data files, per-episode arrays, frames).
// Opening a dataset is in lerobot_open.cpp, the version-specific tables in lerobot_v2.cpp and
// lerobot_v3.cpp.
#include "data/lerobot.h"

#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <deque>

#include "core/error.h"
#include "core/text.h"
#include "data/embodiments.h"
#include "io/parquet.h"
#include "io/video.h"

namespace fs = std::filesystem;

namespace dojo::data {

namespace {

constexpr double kTimestampTolerance = 1e-4;  // seconds, as LeRobot's tolerance_s

Modality layout_modality(const std::vector<std::pair<std::string, int>>& state,
                         const std::vector<std::pair<std::string, int>>& action, const std::string& camera) {
  Modality m;
  int at = 0;
  for (const auto& [key, width] : state) m.state.push_back({key, at, at + width, ""}), at += width;
  at = 0;
  for (const auto& [key, width] : action) m.action.push_back({key, at, at + width, ""}), at += width;
  m.video[camera] = "observation.images." + camera;
  return m;
}

std::vector<RobotLayout> make_layouts() {
  std::vector<RobotLayout> out;
  // GR-1: 44-d state/action as stored; the slot takes 29 of them in its own order.
  const std::vector<std::pair<std::string, int>> gr1 = {{"left_arm", 7},  {"left_hand", 6}, {"left_leg", 6},
                                                        {"neck", 3},      {"right_arm", 7}, {"right_hand", 6},
                                                        {"right_leg", 6}, {"waist", 3}};
  out.push_back({"gr1",
                 slots::kGr1,
                 "ego_view_freq20",
                 {{"left_arm", 7}, {"right_arm", 7}, {"left_hand", 6}, {"right_hand", 6}, {"waist", 3}},
                 layout_modality(gr1, gr1, "ego_view_freq20")});
  const std::vector<std::pair<std::string, int>> g1 = {{"left_leg", 6},  {"right_leg", 6}, {"waist", 3},
                                                       {"left_arm", 7},  {"left_hand", 7}, {"right_arm", 7},
                                                       {"right_hand", 7}};
  out.push_back({"g1", slots::kG1, "ego_view", g1, layout_modality(g1, g1, "ego_view")});
  const std::vector<std::pair<std::string, int>> yam_state = {
      {"ee_pose_obs_left", 16},     {"ee_pose_obs_right", 16}, {"gripper_pos_obs_left", 1},
      {"gripper_pos_obs_right", 1}, {"joint_pos_obs_left", 6}, {"joint_pos_obs_right", 6}};
  const std::vector<std::pair<std::string, int>> yam_action = {
      {"ee_pose_action_left", 16},     {"ee_pose_action_right", 16}, {"gripper_pos_action_left", 1},
      {"gripper_pos_action_right", 1}, {"joint_pos_action_left", 6}, {"joint_pos_action_right", 6}};
  out.push_back({"yam", slots::kYam, "top_camera-images-rgb", yam_action,
                 layout_modality(yam_state, yam_action, "top_camera-images-rgb")});
  const std::vector<std::pair<std::string, int>> agibot_state = {{"left_arm_joint_position", 7},
                                                                 {"right_arm_joint_position", 7},
                                                                 {"left_effector_position", 1},
                                                                 {"right_effector_position", 1},
                                                                 {"head_position", 2},
                                                                 {"waist_pitch", 1},
                                                                 {"waist_lift", 1}};
  auto agibot_action = agibot_state;
  agibot_action.push_back({"robot_velocity", 2});
  out.push_back({"agibot", slots::kAgibot, "top_head", agibot_action,
                 layout_modality(agibot_state, agibot_action, "top_head")});
  return out;
}

}  // namespace

const ModalityRange* Modality::find_action(const std::string& key) const {
  for (const auto& r : action)
    if (r.key == key) return &r;
  return nullptr;
}

Modality Modality::from_json(const nlohmann::json& j, const std::string& where) {
  if (!j.is_object()) throw Error(where + ": modality must be a JSON object");
  Modality m;
  auto ranges = [&](const char* group, std::vector<ModalityRange>& out) {
    if (!j.contains(group)) return;
    const auto& g = j.at(group);
    if (!g.is_object()) throw Error(where + ": '" + group + "' must be an object");
    for (const auto& [key, v] : g.items()) {
      const std::string field = where + ": " + group + "." + key;
      if (!v.is_object() || !v.contains("start") || !v.contains("end") ||
          !v.at("start").is_number_integer() || !v.at("end").is_number_integer())
        throw Error(field + ": needs integer 'start' and 'end'");
      ModalityRange r;
      r.key = key;
      r.start = v.at("start").get<int>();
      r.end = v.at("end").get<int>();
      if (r.start < 0 || r.end <= r.start)
        throw Error(field + ": bad range [" + std::to_string(r.start) + ", " + std::to_string(r.end) + ")");
      if (v.contains("original_key")) {
        if (!v.at("original_key").is_string()) throw Error(field + ": 'original_key' must be a string");
        r.original_key = v.at("original_key").get<std::string>();
      }
      out.push_back(r);
    }
  };
  ranges("state", m.state);
  ranges("action", m.action);
  if (j.contains("video")) {
    if (!j.at("video").is_object()) throw Error(where + ": 'video' must be an object");
    for (const auto& [key, v] : j.at("video").items())
      m.video[key] =
          v.is_object() ? v.value("original_key", "observation.images." + key) : "observation.images." + key;
  }
  if (j.contains("annotation") && j.at("annotation").is_object())
    for (const auto& [key, v] : j.at("annotation").items()) m.annotation.push_back(key);
  return m;
}

namespace {
std::deque<RobotLayout>& layout_table() {  // a deque: find_robot_layout's pointers stay valid
  static std::deque<RobotLayout> layouts = [] {
    const auto built_in = make_layouts();
    return std::deque<RobotLayout>(built_in.begin(), built_in.end());
  }();
  return layouts;
}
}  // namespace

const std::deque<RobotLayout>& robot_layouts() { return layout_table(); }

void add_robot_layout(RobotLayout layout) { layout_table().push_back(std::move(layout)); }

const RobotLayout* find_robot_layout(const std::string& name) {
  for (const auto& l : robot_layouts())
    if (l.name == name) return &l;
  return nullptr;
}

std::string detect_robot(const std::string& robot_type) {
  // A robot of the user's table is named exactly, ahead of the built-in robots' substrings.
  if (auto user = user_robot_for(robot_type); !user.empty()) return user;
  const std::string text = ascii_lower(robot_type);
  if (text.find("gr1") != std::string::npos || text.find("gr-1") != std::string::npos ||
      text.find("fourier") != std::string::npos)
    return "gr1";
  if (text.find("g1") != std::string::npos) return "g1";
  if (text.find("yam") != std::string::npos) return "yam";
  if (text.find("agibot") != std::string::npos) return "agibot";
  return "";
}

std::string format_path_template(const std::string& pattern,
                                 const std::map<std::string, std::string>& strings,
                                 const std::map<std::string, int64_t>& numbers, const std::string& where) {
  std::string out;
  size_t i = 0;
  while (i < pattern.size()) {
    if (pattern[i] != '{') {
      out += pattern[i++];
      continue;
    }
    const size_t close = pattern.find('}', i);
    if (close == std::string::npos)
      throw Error(where + ": unterminated '{' in path template '" + pattern + "'");
    const std::string field = pattern.substr(i + 1, close - i - 1);
    const size_t colon = field.find(':');
    const std::string name = field.substr(0, colon);
    const std::string spec = colon == std::string::npos ? "" : field.substr(colon + 1);
    if (strings.count(name)) {
      out += strings.at(name);
    } else if (numbers.count(name)) {
      std::string digits = std::to_string(numbers.at(name));
      if (!spec.empty() && spec[0] == '0') {
        const size_t width = static_cast<size_t>(std::atoi(spec.c_str() + 1));
        if (digits.size() < width) digits = std::string(width - digits.size(), '0') + digits;
      }
      out += digits;
    } else {
      throw Error(where + ": unknown field '{" + name + "}' in path template '" + pattern + "'");
    }
    i = close + 1;
  }
  return out;
}

// Decoded columns of one data parquet file.
struct LeRobotDataset::DataFile {
  std::vector<int64_t> episode_index;
  std::vector<float> timestamp;
  std::map<std::string, io::ParquetList<float>> lists;  // action, observation.state, original keys
};

std::string LeRobotDataset::episode_location(size_t index) const {
  DOJO_CHECK(index < episodes_.size(),
             root_.string() + ": episode " + std::to_string(index) + " out of range");
  return episodes_[index].data_file.string() + " (episode " + std::to_string(episodes_[index].index) + ")";
}

fs::path LeRobotDataset::video_file(size_t index) const { return episodes_.at(index).video_file; }
fs::path LeRobotDataset::data_file(size_t index) const { return episodes_.at(index).data_file; }

std::shared_ptr<const LeRobotDataset::DataFile> LeRobotDataset::load_data(const fs::path& path) const {
  {
    std::lock_guard<std::mutex> lock(cache_mutex_);
    auto it = cache_.find(path.string());
    if (it != cache_.end()) return it->second;
  }
  if (!fs::exists(path)) throw Error(path.string() + ": data file missing");
  const auto file = io::ParquetFile::open(path);
  auto data = std::make_shared<DataFile>();
  data->episode_index = file.read_i64("episode_index");
  data->timestamp = file.has_column("timestamp") ? file.read_f32("timestamp")
                                                 : std::vector<float>(data->episode_index.size(), 0.f);
  std::vector<std::string> lists;
  if (file.has_column("action")) lists.push_back("action");
  if (file.has_column("observation.state")) lists.push_back("observation.state");
  for (const auto& r : modality_.action)
    if (!r.original_key.empty()) lists.push_back(r.original_key);
  for (const auto& name : lists)
    if (!data->lists.count(name)) {
      if (!file.has_column(name))
        throw Error(path.string() + ": no column '" + name + "' (named by meta/modality.json)");
      data->lists[name] = file.read_list_f32(name);
    }
  std::lock_guard<std::mutex> lock(cache_mutex_);
  // Small bounded cache: v3.0 files hold many episodes and clips hit them repeatedly.
  if (cache_.size() >= 8) cache_.erase(cache_.begin());
  cache_[path.string()] = data;
  return data;
}

std::vector<int64_t> LeRobotDataset::episode_rows(size_t index, const DataFile& data) const {
  const Episode& ep = episodes_.at(index);
  std::vector<int64_t> rows;
  for (size_t r = 0; r < data.episode_index.size(); ++r)
    if (data.episode_index[r] == ep.index) rows.push_back(static_cast<int64_t>(r));
  if (static_cast<int64_t>(rows.size()) != ep.length)
    throw Error(ep.data_file.string() + ": episode " + std::to_string(ep.index) + " has " +
                std::to_string(rows.size()) + " rows, the episode table says " + std::to_string(ep.length));
  return rows;
}

namespace {

// Rows `rows` of a list column, columns [start, end) of each, as [T, end - start].
at::Tensor gather_rows(const io::ParquetList<float>& list, const std::vector<int64_t>& rows, int start,
                       int end, const std::string& where, const std::string& column) {
  auto out = torch::empty({static_cast<int64_t>(rows.size()), end - start}, torch::kFloat32);
  float* dst = out.data_ptr<float>();
  for (size_t i = 0; i < rows.size(); ++i) {
    const int64_t begin = list.offsets[rows[i]];
    const int64_t width = list.offsets[rows[i] + 1] - begin;
    if (width < end)
      throw Error(where + ": column '" + column + "' row " + std::to_string(rows[i]) + " has " +
                  std::to_string(width) + " values, needs " + std::to_string(end));
    std::copy(list.values.begin() + begin + start, list.values.begin() + begin + end,
              dst + i * (end - start));
  }
  return out;
}

int list_width(const io::ParquetList<float>& list, const std::vector<int64_t>& rows) {
  return rows.empty() ? 0 : static_cast<int>(list.offsets[rows[0] + 1] - list.offsets[rows[0]]);
}

}  // namespace

EpisodeData LeRobotDataset::read_raw(size_t index) const {
  const auto data = load_data(episodes_.at(index).data_file);
  const auto rows = episode_rows(index, *data);
  const std::string where = episodes_[index].data_file.string();
  EpisodeData out;
  for (const char* name : {"action", "observation.state"}) {
    if (!data->lists.count(name)) continue;
    const auto& list = data->lists.at(name);
    const int width = list_width(list, rows);
    for (int64_t r : rows)
      if (list.offsets[r + 1] - list.offsets[r] != width)
        throw Error(where + ": column '" + name + "' rows have different lengths");
    (std::string(name) == "action" ? out.actions : out.states) =
        gather_rows(list, rows, 0, width, where, name);
  }
  return out;
}

EpisodeData LeRobotDataset::read_arrays(size_t index) const {
  const Episode& ep = episodes_.at(index);
  const auto data = load_data(ep.data_file);
  const auto rows = episode_rows(index, *data);
  const std::string where = ep.data_file.string();
  EpisodeData out;
  if (info_.embodiment == Embodiment::kRobot) {
    if (layout_) {
      std::vector<at::Tensor> parts;
      for (const auto& [key, width] : layout_->action_order) {
        const ModalityRange* r = modality_.find_action(key);
        const std::string column = r->original_key.empty() ? "action" : r->original_key;
        if (!data->lists.count(column)) throw Error(where + ": no column '" + column + "'");
        parts.push_back(
            gather_rows(data->lists.at(column), rows, r->start, r->end, where, column));  // [T, w]
      }
      out.actions = torch::cat(parts, 1);  // [T, slot width]
    } else if (data->lists.count("action")) {
      out.actions = gather_rows(data->lists.at("action"), rows, 0, list_width(data->lists.at("action"), rows),
                                where, "action");
    }
  }
  if (data->lists.count("observation.state")) {
    const auto& list = data->lists.at("observation.state");
    out.states = gather_rows(list, rows, 0, list_width(list, rows), where, "observation.state");  // [T, S]
  }
  for (const auto* t : {&out.actions, &out.states})
    if (t->defined() && !torch::isfinite(*t).all().item<bool>())
      throw Error(where + ": episode " + std::to_string(ep.index) + " has NaN or Inf in its actions/states");
  out.meta["task"] = ep.tasks.empty() ? "" : ep.tasks.front();
  out.meta["tasks"] = ep.tasks;
  out.meta["episode_index"] = ep.index;
  return out;
}

at::Tensor LeRobotDataset::read_frames(size_t index, const std::vector<int64_t>& frames) const {
  const Episode& ep = episodes_.at(index);
  const auto data = load_data(ep.data_file);
  const auto rows = episode_rows(index, *data);
  if (!fs::exists(ep.video_file))
    throw Error(ep.video_file.string() + ": video file missing (episode " + std::to_string(ep.index) + ")");
  io::VideoReaderOptions reader_options;
  reader_options.threads = 1;  // the loader's parallelism comes from its workers
  io::VideoReader reader(ep.video_file.string(), reader_options);
  const double fps = reader.info().fps > 0 ? reader.info().fps : info_.fps;
  const int64_t video_frames = reader.num_frames();
  bool all_zero = true;
  for (int64_t r : rows) all_zero = all_zero && data->timestamp[r] == 0.f;
  std::vector<int64_t> picks;
  for (int64_t k : frames) {
    if (k < 0 || k >= static_cast<int64_t>(rows.size()))
      throw Error(ep.data_file.string() + ": frame " + std::to_string(k) + " outside episode " +
                  std::to_string(ep.index) + " (" + std::to_string(rows.size()) + " rows)");
    const double t = ep.from_timestamp + (all_zero ? k / info_.fps : double(data->timestamp[rows[k]]));
    const int64_t frame = std::llround(t * fps);
    const bool beyond_span = ep.to_timestamp >= 0 && t > ep.to_timestamp + kTimestampTolerance;
    if (frame < 0 || frame >= video_frames || beyond_span)
      throw Error(ep.video_file.string() + ": timestamp " + std::to_string(t) + " s of episode " +
                  std::to_string(ep.index) + " is outside the video (" + std::to_string(video_frames) +
                  " frames at " + std::to_string(fps) + " fps)");
    if (std::abs(frame / fps - t) > kTimestampTolerance)
      throw Error(ep.video_file.string() + ": no frame within 1e-4 s of timestamp " + std::to_string(t) +
                  " s (episode " + std::to_string(ep.index) + ")");
    picks.push_back(frame);
  }
  return reader.read_frames(picks);  // [N, H, W, 3] u8
}

nlohmann::json LeRobotDataset::describe() const {
  nlohmann::json j = EpisodeSource::describe();
  j["codebase_version"] = info_json_.value("codebase_version", "");
  j["robot_type"] = info_json_.value("robot_type", "");
  j["robot"] = robot_;
  j["cameras"] = cameras_;
  j["camera"] = camera_;
  j["tasks"] = tasks_;
  j["raw_action_dim"] = action_width_;
  nlohmann::json keys = nlohmann::json::object();
  for (const auto& r : modality_.action) keys["action." + r.key] = {r.start, r.end};
  for (const auto& r : modality_.state) keys["state." + r.key] = {r.start, r.end};
  j["modality"] = keys;
  return j;
}

}  // namespace dojo::data