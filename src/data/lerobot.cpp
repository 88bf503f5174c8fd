#include "data/lerobot.h"

#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <fstream>

#include "core/error.h"
#include "core/json_file.h"
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

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

std::vector<nlohmann::json> read_jsonl(const fs::path& path) {
  std::ifstream in(path);
  if (!in) throw Error(path.string() + ": cannot open");
  std::vector<nlohmann::json> out;
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
    try {
      out.push_back(nlohmann::json::parse(line));
    } catch (const nlohmann::json::exception& e) {
      throw Error(path.string() + ": line " + std::to_string(number) + ": invalid JSON: " + e.what());
    }
  }
  return out;
}

// "0:100" -> [0, 100)
std::pair<int64_t, int64_t> parse_range(const std::string& s, const std::string& where) {
  const auto colon = s.find(':');
  try {
    if (colon != std::string::npos) return {std::stoll(s.substr(0, colon)), std::stoll(s.substr(colon + 1))};
  } catch (const std::exception&) {
  }
  throw Error(where + ": split range '" + s + "' is not START:END");
}

ArrayStats stats_from_json(const nlohmann::json& j, const std::string& where) {
  ArrayStats s;
  try {
    s.min = j.at("min").get<std::vector<float>>();
    s.max = j.at("max").get<std::vector<float>>();
    s.mean = j.contains("mean") ? j.at("mean").get<std::vector<float>>() : s.min;
    s.std = j.contains("std") ? j.at("std").get<std::vector<float>>() : std::vector<float>(s.min.size(), 0.f);
  } catch (const nlohmann::json::exception& e) {
    throw Error(where + ": " + e.what());
  }
  if (s.max.size() != s.min.size() || s.mean.size() != s.min.size() || s.std.size() != s.min.size())
    throw Error(where + ": min/max/mean/std have different lengths");
  return s;
}

ArrayStats slice_stats(const ArrayStats& s, int start, int end) {
  ArrayStats out;
  out.min.assign(s.min.begin() + start, s.min.begin() + end);
  out.max.assign(s.max.begin() + start, s.max.begin() + end);
  out.mean.assign(s.mean.begin() + start, s.mean.begin() + end);
  out.std.assign(s.std.begin() + start, s.std.begin() + end);
  return out;
}

void append_stats(ArrayStats& a, const ArrayStats& b) {
  a.min.insert(a.min.end(), b.min.begin(), b.min.end());
  a.max.insert(a.max.end(), b.max.begin(), b.max.end());
  a.mean.insert(a.mean.end(), b.mean.begin(), b.mean.end());
  a.std.insert(a.std.end(), b.std.begin(), b.std.end());
}

// Feature width from info.json ("shape": [44]).
int feature_width(const nlohmann::json& features, const std::string& key) {
  if (!features.contains(key)) return 0;
  const auto& shape = features.at(key).value("shape", nlohmann::json::array());
  if (!shape.is_array() || shape.empty() || !shape[0].is_number_integer()) return 0;
  int64_t width = 1;
  for (const auto& d : shape) width *= d.get<int64_t>();
  return static_cast<int>(width);
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

const std::vector<RobotLayout>& robot_layouts() {
  static const std::vector<RobotLayout> layouts = make_layouts();
  return layouts;
}

const RobotLayout* find_robot_layout(const std::string& name) {
  for (const auto& l : robot_layouts())
    if (l.name == name) return &l;
  return nullptr;
}

std::string detect_robot(const std::string& path, const std::string& robot_type) {
  const std::string text = lower(path + " " + robot_type);
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

std::shared_ptr<LeRobotDataset> LeRobotDataset::open(const fs::path& root, const OpenOptions& options) {
  auto ds = std::shared_ptr<LeRobotDataset>(new LeRobotDataset());
  ds->root_ = root;
  const fs::path info_path = root / "meta" / "info.json";
  ds->info_json_ = read_json_file(info_path);
  const auto& ij = ds->info_json_;
  const std::string where = info_path.string();
  const std::string version = ij.value("codebase_version", "");
  const bool v3 = version.rfind("v3", 0) == 0;
  if (!v3 && version.rfind("v2", 0) != 0)
    throw Error(where + ": codebase_version '" + version + "' not supported (v2.0, v2.1 or v3.0)");
  ds->format_ = "lerobot-" + version;
  if (!ij.contains("features") || !ij.at("features").is_object())
    throw Error(where + ": field 'features' missing");
  const auto& features = ij.at("features");
  if (!ij.contains("fps") || !ij.at("fps").is_number()) throw Error(where + ": field 'fps' missing");

  DatasetInfo& info = ds->info_;
  info.name = dataset_name(root);
  info.fps = ij.at("fps").get<double>();
  ds->action_width_ = feature_width(features, "action");
  ds->state_width_ = feature_width(features, "observation.state");
  for (const auto& [key, f] : features.items())
    if (f.is_object() && f.value("dtype", "") == "video") ds->cameras_.push_back(key);

  // Robot and modality.
  const std::string robot_type = ij.value("robot_type", "");
  ds->robot_ = options.embodiment == "auto" ? detect_robot(fs::absolute(root).string(), robot_type)
                                            : options.embodiment;
  if (ds->robot_ != "human" && ds->robot_ != "none" && !ds->robot_.empty()) {
    ds->layout_ = find_robot_layout(ds->robot_);
    if (ds->layout_ == nullptr)
      throw Error(root.string() + ": unknown embodiment '" + ds->robot_ +
                  "' (gr1, g1, yam, agibot, human, none)");
  }
  const fs::path modality_path = root / "meta" / "modality.json";
  std::string modality_where = modality_path.string();
  if (fs::exists(modality_path)) {
    ds->modality_ = Modality::from_json(read_json_file(modality_path), modality_path.string());
  } else if (ds->layout_) {
    ds->modality_ = ds->layout_->default_modality;
    modality_where = root.string() + ": built-in " + ds->layout_->name + " layout";
  }
  for (const auto& r : ds->modality_.action)
    if (r.original_key.empty() && ds->action_width_ > 0 && r.end > ds->action_width_)
      throw Error(modality_where + ": action." + r.key + " ends at " + std::to_string(r.end) +
                  " beyond the " + std::to_string(ds->action_width_) + "-d action feature");
  for (const auto& r : ds->modality_.state)
    if (r.original_key.empty() && ds->state_width_ > 0 && r.end > ds->state_width_)
      throw Error(modality_where + ": state." + r.key + " ends at " + std::to_string(r.end) + " beyond the " +
                  std::to_string(ds->state_width_) + "-d state feature");

  // Camera: explicit, else the robot's, else the first video feature.
  if (!options.camera.empty()) {
    std::string cam = options.camera;
    if (ds->modality_.video.count(cam)) cam = ds->modality_.video.at(cam);
    if (cam.rfind("video.", 0) == 0 && ds->modality_.video.count(cam.substr(6)))
      cam = ds->modality_.video.at(cam.substr(6));
    if (std::find(ds->cameras_.begin(), ds->cameras_.end(), cam) == ds->cameras_.end())
      throw Error(where + ": no video feature '" + options.camera + "'");
    ds->camera_ = cam;
  } else if (ds->layout_ && ds->modality_.video.count(ds->layout_->camera) &&
             std::find(ds->cameras_.begin(), ds->cameras_.end(),
                       ds->modality_.video.at(ds->layout_->camera)) != ds->cameras_.end()) {
    ds->camera_ = ds->modality_.video.at(ds->layout_->camera);
  } else if (!ds->cameras_.empty()) {
    ds->camera_ = ds->cameras_.front();
  }
  if (ds->camera_.empty()) throw Error(where + ": no video feature (dtype \"video\") to read frames from");
  {
    const auto& cam = features.at(ds->camera_);
    const auto shape = cam.value("shape", nlohmann::json::array());
    const auto vinfo = cam.value("info", nlohmann::json::object());
    info.height =
        vinfo.value("video.height", shape.size() == 3 && shape[0].is_number() ? shape[0].get<int>() : 0);
    info.width =
        vinfo.value("video.width", shape.size() == 3 && shape[1].is_number() ? shape[1].get<int>() : 0);
  }

  // Tasks.
  if (v3) {
    const fs::path tasks_path = root / "meta" / "tasks.parquet";
    if (fs::exists(tasks_path)) {
      const auto file = io::ParquetFile::open(tasks_path);
      const auto ids = file.read_i64("task_index");
      std::string text_column = file.has_column("task") ? "task" : "__index_level_0__";
      const auto texts = file.read_string(text_column);
      for (size_t i = 0; i < ids.size(); ++i) {
        if (ids[i] < 0 || ids[i] > 1000000) throw Error(tasks_path.string() + ": task_index out of range");
        if (static_cast<size_t>(ids[i]) >= ds->tasks_.size())
          ds->tasks_.resize(static_cast<size_t>(ids[i]) + 1);
        ds->tasks_[static_cast<size_t>(ids[i])] = texts[i];
      }
    }
  } else {
    const fs::path tasks_path = root / "meta" / "tasks.jsonl";
    if (fs::exists(tasks_path))
      for (const auto& t : read_jsonl(tasks_path)) {
        const int64_t id = t.value("task_index", int64_t(-1));
        if (id < 0 || id > 1000000) throw Error(tasks_path.string() + ": task_index out of range");
        if (static_cast<size_t>(id) >= ds->tasks_.size()) ds->tasks_.resize(static_cast<size_t>(id) + 1);
        ds->tasks_[static_cast<size_t>(id)] = t.value("task", "");
      }
  }

  // Episodes.
  const int64_t chunks_size = ij.value("chunks_size", int64_t(1000));
  const std::string data_tmpl =
      ij.value("data_path", v3 ? "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
                               : "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet");
  const std::string video_tmpl = ij.value(
      "video_path", v3 ? "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
                       : "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4");
  if (v3) {
    std::vector<fs::path> files;
    const fs::path dir = root / "meta" / "episodes";
    if (!fs::exists(dir)) throw Error(dir.string() + ": missing (LeRobot v3.0 episode table)");
    for (const auto& e : fs::recursive_directory_iterator(dir))
      if (e.is_regular_file() && e.path().extension() == ".parquet") files.push_back(e.path());
    std::sort(files.begin(), files.end());
    if (files.empty()) throw Error(dir.string() + ": no episode parquet files");
    const std::string vk = "videos/" + ds->camera_ + "/";
    for (const auto& path : files) {
      const auto file = io::ParquetFile::open(path);
      const auto index = file.read_i64("episode_index");
      const auto length = file.read_i64("length");
      const auto data_chunk = file.read_i64("data/chunk_index");
      const auto data_file = file.read_i64("data/file_index");
      if (!file.has_column(vk + "chunk_index"))
        throw Error(path.string() + ": no column '" + vk + "chunk_index' for camera '" + ds->camera_ + "'");
      const auto video_chunk = file.read_i64(vk + "chunk_index");
      const auto video_file = file.read_i64(vk + "file_index");
      const auto from = file.read_f64(vk + "from_timestamp");
      const auto to = file.read_f64(vk + "to_timestamp");
      io::ParquetList<std::string> tasks;
      if (file.has_column("tasks")) tasks = file.read_list_string("tasks");
      for (size_t i = 0; i < index.size(); ++i) {
        Episode ep;
        ep.index = index[i];
        ep.length = length[i];
        if (tasks.rows() == static_cast<int64_t>(index.size()))
          ep.tasks.assign(tasks.values.begin() + tasks.offsets[i],
                          tasks.values.begin() + tasks.offsets[i + 1]);
        ep.data_file =
            root / format_path_template(
                       data_tmpl, {}, {{"chunk_index", data_chunk[i]}, {"file_index", data_file[i]}}, where);
        ep.video_file = root / format_path_template(
                                   video_tmpl, {{"video_key", ds->camera_}},
                                   {{"chunk_index", video_chunk[i]}, {"file_index", video_file[i]}}, where);
        ep.from_timestamp = from[i];
        ep.to_timestamp = to[i];
        ds->episodes_.push_back(std::move(ep));
      }
    }
  } else {
    const fs::path episodes_path = root / "meta" / "episodes.jsonl";
    for (const auto& e : read_jsonl(episodes_path)) {
      Episode ep;
      try {
        ep.index = e.at("episode_index").get<int64_t>();
        ep.length = e.at("length").get<int64_t>();
        if (e.contains("tasks")) ep.tasks = e.at("tasks").get<std::vector<std::string>>();
      } catch (const nlohmann::json::exception& ex) {
        throw Error(episodes_path.string() + ": " + ex.what());
      }
      const std::map<std::string, int64_t> numbers = {
          {"episode_chunk", ep.index / std::max<int64_t>(1, chunks_size)}, {"episode_index", ep.index}};
      ep.data_file = root / format_path_template(data_tmpl, {}, numbers, where);
      ep.video_file = root / format_path_template(video_tmpl, {{"video_key", ds->camera_}}, numbers, where);
      ds->episodes_.push_back(std::move(ep));
    }
  }
  std::sort(ds->episodes_.begin(), ds->episodes_.end(),
            [](const Episode& a, const Episode& b) { return a.index < b.index; });

  // Splits from info.json ("train": "0:90"); episodes outside every range are "train".
  std::vector<std::pair<std::string, std::pair<int64_t, int64_t>>> splits;
  if (ij.contains("splits") && ij.at("splits").is_object())
    for (const auto& [name, range] : ij.at("splits").items())
      if (range.is_string())
        splits.push_back({name, parse_range(range.get<std::string>(), where + ": splits." + name)});
  for (const auto& ep : ds->episodes_) {
    EpisodeEntry entry;
    char id[32];
    std::snprintf(id, sizeof id, "episode_%06lld", static_cast<long long>(ep.index));
    entry.id = id;
    entry.frames = ep.length;
    entry.split = "train";
    for (const auto& [name, range] : splits)
      if (ep.index >= range.first && ep.index < range.second) {
        entry.split = name;
        break;
      }
    entry.task = ep.tasks.empty() ? "" : ep.tasks.front();
    info.episodes.push_back(entry);
  }

  // Embodiment, action width and statistics.
  info.embodiment = ds->robot_ == "human" ? Embodiment::kHuman : Embodiment::kRobot;
  info.state_dim = ds->state_width_;
  ArrayStats raw_action_stats, raw_state_stats;
  bool have_action_stats = false, have_state_stats = false;
  std::map<std::string, ArrayStats> column_stats;
  const fs::path stats_path = root / "meta" / "stats.json";
  const fs::path episode_stats_path = root / "meta" / "episodes_stats.jsonl";
  if (fs::exists(stats_path)) {
    const auto sj = read_json_file(stats_path);
    for (const auto& [key, v] : sj.items())
      if (v.is_object() && v.contains("min") && v.contains("max") && v.at("min").is_array() &&
          (v.at("min").empty() || v.at("min")[0].is_number()))
        column_stats[key] = stats_from_json(v, stats_path.string() + ": " + key);
  } else if (fs::exists(episode_stats_path)) {
    // v2.1: per-episode stats; pooled here (min of mins, max of maxes, count-weighted moments).
    std::map<std::string, std::vector<double>> mn, mx, sum, sq;
    std::map<std::string, double> total;
    for (const auto& line : read_jsonl(episode_stats_path)) {
      if (!line.contains("stats") || !line.at("stats").is_object()) continue;
      for (const auto& [key, v] : line.at("stats").items()) {
        if (key != "action" && key != "observation.state") continue;
        const ArrayStats s = stats_from_json(v, episode_stats_path.string() + ": " + key);
        double count = 1;
        if (v.contains("count") && v.at("count").is_array() && !v.at("count").empty())
          count = v.at("count")[0].get<double>();
        auto& a = mn[key];
        if (a.empty()) {
          a.assign(s.min.begin(), s.min.end());
          mx[key].assign(s.max.begin(), s.max.end());
          sum[key].assign(s.min.size(), 0.0);
          sq[key].assign(s.min.size(), 0.0);
        }
        if (a.size() != s.min.size())
          throw Error(episode_stats_path.string() + ": " + key + " widths differ between episodes");
        for (size_t d = 0; d < s.min.size(); ++d) {
          a[d] = std::min<double>(a[d], s.min[d]);
          mx[key][d] = std::max<double>(mx[key][d], s.max[d]);
          sum[key][d] += count * s.mean[d];
          sq[key][d] += count * (double(s.std[d]) * s.std[d] + double(s.mean[d]) * s.mean[d]);
        }
        total[key] += count;
      }
    }
    for (const auto& [key, a] : mn) {
      ArrayStats s;
      for (size_t d = 0; d < a.size(); ++d) {
        const double mean = sum[key][d] / total[key];
        s.min.push_back(static_cast<float>(a[d]));
        s.max.push_back(static_cast<float>(mx[key][d]));
        s.mean.push_back(static_cast<float>(mean));
        s.std.push_back(static_cast<float>(std::sqrt(std::max(0.0, sq[key][d] / total[key] - mean * mean))));
      }
      column_stats[key] = s;
    }
  }
  if (column_stats.count("action")) raw_action_stats = column_stats.at("action"), have_action_stats = true;
  if (column_stats.count("observation.state"))
    raw_state_stats = column_stats.at("observation.state"), have_state_stats = true;
  if (have_state_stats && raw_state_stats.dim() == ds->state_width_) info.state_stats = raw_state_stats;

  if (info.embodiment == Embodiment::kRobot && ds->layout_) {
    info.action_slot = ds->layout_->slot.name;
    ArrayStats mapped;
    bool stats_ok = true;
    for (const auto& [key, width] : ds->layout_->action_order) {
      const ModalityRange* r = ds->modality_.find_action(key);
      if (r == nullptr)
        throw Error(root.string() + ": modality has no action key '" + key + "' needed for " +
                    ds->layout_->name);
      if (r->width() != width)
        throw Error(root.string() + ": action." + key + " is " + std::to_string(r->width()) + "-d, " +
                    ds->layout_->name + " expects " + std::to_string(width));
      for (int d = r->start; d < r->end; ++d)
        info.action_names.push_back(key + "." + std::to_string(d - r->start));
      const std::string column = r->original_key.empty() ? "action" : r->original_key;
      if (column_stats.count(column) && column_stats.at(column).dim() >= r->end)
        append_stats(mapped, slice_stats(column_stats.at(column), r->start, r->end));
      else
        stats_ok = false;
    }
    info.action_dim = static_cast<int>(info.action_names.size());
    if (stats_ok) info.action_stats = mapped;
  } else if (info.embodiment == Embodiment::kRobot) {
    // Unknown robot: the raw action column, not placed in any slot (ClipDataset refuses it).
    info.action_dim = ds->action_width_;
    if (have_action_stats && raw_action_stats.dim() == ds->action_width_)
      info.action_stats = raw_action_stats;
  }
  return ds;
}

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
