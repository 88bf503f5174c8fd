// Opening a LeRobot dataset: LeRobotDataset::open and its steps (info.json, robot and modality,
// camera, the version's task and episode tables, splits, statistics and the action mapping).
// The version-specific tables are read in lerobot_v2.cpp and lerobot_v3.cpp.
#include "data/lerobot.h"

#include <algorithm>
#include <cstdio>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "core/error.h"
#include "core/json_file.h"
#include "data/embodiments.h"
#include "data/lerobot_internal.h"

namespace fs = std::filesystem;

namespace dojo::data {

namespace {

// "0:100" -> [0, 100)
std::pair<int64_t, int64_t> parse_range(const std::string& s, const std::string& where) {
  const auto colon = s.find(':');
  try {
    if (colon != std::string::npos) return {std::stoll(s.substr(0, colon)), std::stoll(s.substr(colon + 1))};
  } catch (const std::exception&) {
  }
  throw Error(where + ": split range '" + s + "' is not START:END");
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

// meta/info.json, named in error messages.
fs::path info_json_path(const fs::path& root) { return root / "meta" / "info.json"; }

// info.json's file templates, with the version's defaults.
PathTemplates path_templates(const nlohmann::json& ij, bool v3) {
  PathTemplates paths;
  paths.chunks_size = ij.value("chunks_size", int64_t(1000));
  paths.data =
      ij.value("data_path", v3 ? "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
                               : "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet");
  paths.video = ij.value("video_path",
                         v3 ? "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
                            : "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4");
  return paths;
}

// Statistics by column ("action", "observation.state", ...) from meta/stats.json, else pooled
// from meta/episodes_stats.jsonl; empty when the dataset has neither.
std::map<std::string, ArrayStats> read_column_stats(const fs::path& root) {
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
    column_stats = pool_episode_stats(episode_stats_path);
  }
  return column_stats;
}

}  // namespace

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

std::shared_ptr<LeRobotDataset> LeRobotDataset::open(const fs::path& root, const OpenOptions& options) {
  auto ds = std::shared_ptr<LeRobotDataset>(new LeRobotDataset());
  ds->root_ = root;
  const bool v3 = ds->read_info_json();
  ds->choose_robot(options);
  ds->choose_camera(options);
  ds->read_episode_table(v3);
  ds->build_episode_entries();
  ds->set_embodiment_and_stats(read_column_stats(root));
  return ds;
}

bool LeRobotDataset::read_info_json() {
  const fs::path info_path = info_json_path(root_);
  info_json_ = read_json_file(info_path);
  const auto& ij = info_json_;
  const std::string where = info_path.string();
  const std::string version = ij.value("codebase_version", "");
  const bool v3 = version.rfind("v3", 0) == 0;
  if (!v3 && version.rfind("v2", 0) != 0)
    throw Error(where + ": codebase_version '" + version + "' not supported (v2.0, v2.1 or v3.0)");
  format_ = "lerobot-" + version;
  if (!ij.contains("features") || !ij.at("features").is_object())
    throw Error(where + ": field 'features' missing");
  const auto& features = ij.at("features");
  if (!ij.contains("fps") || !ij.at("fps").is_number()) throw Error(where + ": field 'fps' missing");

  DatasetInfo& info = info_;
  info.name = dataset_name(root_);
  info.fps = ij.at("fps").get<double>();
  action_width_ = feature_width(features, "action");
  state_width_ = feature_width(features, "observation.state");
  for (const auto& [key, f] : features.items())
    if (f.is_object() && f.value("dtype", "") == "video") cameras_.push_back(key);
  return v3;
}

void LeRobotDataset::choose_robot(const OpenOptions& options) {
  // Robot and modality.
  const auto& ij = info_json_;
  const std::string robot_type = ij.value("robot_type", "");
  robot_ = options.embodiment == "auto" ? detect_robot(robot_type) : options.embodiment;
  if (robot_ != "human" && robot_ != "none" && !robot_.empty()) {
    layout_ = find_robot_layout(robot_);
    if (layout_ == nullptr)
      throw Error(root_.string() + ": unknown embodiment '" + robot_ + "' (" + embodiment_names() +
                  ", human, none; a new robot: --embodiments FILE, docs/new_robot.md)");
  }
  const fs::path modality_path = root_ / "meta" / "modality.json";
  std::string modality_where = modality_path.string();
  if (fs::exists(modality_path)) {
    modality_ = Modality::from_json(read_json_file(modality_path), modality_path.string());
  } else if (layout_) {
    modality_ = layout_->default_modality;
    modality_where = root_.string() + ": built-in " + layout_->name + " layout";
  }
  for (const auto& r : modality_.action)
    if (r.original_key.empty() && action_width_ > 0 && r.end > action_width_)
      throw Error(modality_where + ": action." + r.key + " ends at " + std::to_string(r.end) +
                  " beyond the " + std::to_string(action_width_) + "-d action feature");
  for (const auto& r : modality_.state)
    if (r.original_key.empty() && state_width_ > 0 && r.end > state_width_)
      throw Error(modality_where + ": state." + r.key + " ends at " + std::to_string(r.end) + " beyond the " +
                  std::to_string(state_width_) + "-d state feature");
}

void LeRobotDataset::choose_camera(const OpenOptions& options) {
  const std::string where = info_json_path(root_).string();
  const auto& features = info_json_.at("features");
  DatasetInfo& info = info_;

  // Camera: explicit, else the robot's, else the first video feature.
  if (!options.camera.empty()) {
    std::string cam = options.camera;
    if (modality_.video.count(cam)) cam = modality_.video.at(cam);
    if (cam.rfind("video.", 0) == 0 && modality_.video.count(cam.substr(6)))
      cam = modality_.video.at(cam.substr(6));
    if (std::find(cameras_.begin(), cameras_.end(), cam) == cameras_.end())
      throw Error(where + ": no video feature '" + options.camera + "'");
    camera_ = cam;
  } else if (layout_ && modality_.video.count(layout_->camera) &&
             std::find(cameras_.begin(), cameras_.end(), modality_.video.at(layout_->camera)) !=
                 cameras_.end()) {
    camera_ = modality_.video.at(layout_->camera);
  } else if (!cameras_.empty()) {
    camera_ = cameras_.front();
  }
  if (camera_.empty()) throw Error(where + ": no video feature (dtype \"video\") to read frames from");
  {
    const auto& cam = features.at(camera_);
    const auto shape = cam.value("shape", nlohmann::json::array());
    const auto vinfo = cam.value("info", nlohmann::json::object());
    info.height =
        vinfo.value("video.height", shape.size() == 3 && shape[0].is_number() ? shape[0].get<int>() : 0);
    info.width =
        vinfo.value("video.width", shape.size() == 3 && shape[1].is_number() ? shape[1].get<int>() : 0);
  }
}

void LeRobotDataset::read_episode_table(bool v3) {
  // Tasks.
  tasks_ = v3 ? read_tasks_v3(root_) : read_tasks_v2(root_);

  // Episodes.
  const PathTemplates paths = path_templates(info_json_, v3);
  const std::string where = info_json_path(root_).string();
  episodes_ =
      v3 ? read_episodes_v3(root_, paths, camera_, where) : read_episodes_v2(root_, paths, camera_, where);
  std::sort(episodes_.begin(), episodes_.end(),
            [](const Episode& a, const Episode& b) { return a.index < b.index; });
}

void LeRobotDataset::build_episode_entries() {
  const auto& ij = info_json_;
  const std::string where = info_json_path(root_).string();
  DatasetInfo& info = info_;

  // Splits from info.json ("train": "0:90"); episodes outside every range are "train".
  std::vector<std::pair<std::string, std::pair<int64_t, int64_t>>> splits;
  if (ij.contains("splits") && ij.at("splits").is_object())
    for (const auto& [name, range] : ij.at("splits").items())
      if (range.is_string())
        splits.push_back({name, parse_range(range.get<std::string>(), where + ": splits." + name)});
  for (const auto& ep : episodes_) {
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
}

void LeRobotDataset::set_embodiment_and_stats(const std::map<std::string, ArrayStats>& column_stats) {
  // Embodiment, action width and statistics.
  DatasetInfo& info = info_;
  info.embodiment = robot_ == "human" ? Embodiment::kHuman : Embodiment::kRobot;
  info.state_dim = state_width_;
  ArrayStats raw_action_stats, raw_state_stats;
  bool have_action_stats = false, have_state_stats = false;
  if (column_stats.count("action")) raw_action_stats = column_stats.at("action"), have_action_stats = true;
  if (column_stats.count("observation.state"))
    raw_state_stats = column_stats.at("observation.state"), have_state_stats = true;
  if (have_state_stats && raw_state_stats.dim() == state_width_) info.state_stats = raw_state_stats;

  if (info.embodiment == Embodiment::kRobot && layout_) {
    info.action_slot = layout_->slot.name;
    ArrayStats mapped;
    bool stats_ok = true;
    for (const auto& [key, width] : layout_->action_order) {
      const ModalityRange* r = modality_.find_action(key);
      if (r == nullptr)
        throw Error(root_.string() + ": modality has no action key '" + key + "' needed for " +
                    layout_->name);
      if (r->width() != width)
        throw Error(root_.string() + ": action." + key + " is " + std::to_string(r->width()) + "-d, " +
                    layout_->name + " expects " + std::to_string(width));
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
    info.action_dim = action_width_;
    if (have_action_stats && raw_action_stats.dim() == action_width_) info.action_stats = raw_action_stats;
  }
}

}  // namespace dojo::data
