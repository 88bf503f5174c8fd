// LeRobot v2.0 / v2.1 tables: meta/tasks.jsonl, meta/episodes.jsonl (one data and one video file
// per episode) and v2.1's per-episode statistics, meta/episodes_stats.jsonl.
#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "core/error.h"
#include "data/lerobot.h"
#include "data/lerobot_internal.h"

namespace fs = std::filesystem;

namespace dojo::data {

namespace {

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

}  // namespace

std::vector<std::string> read_tasks_v2(const fs::path& root) {
  std::vector<std::string> tasks;
  const fs::path tasks_path = root / "meta" / "tasks.jsonl";
  if (fs::exists(tasks_path))
    for (const auto& t : read_jsonl(tasks_path)) {
      const int64_t id = t.value("task_index", int64_t(-1));
      if (id < 0 || id > 1000000) throw Error(tasks_path.string() + ": task_index out of range");
      if (static_cast<size_t>(id) >= tasks.size()) tasks.resize(static_cast<size_t>(id) + 1);
      tasks[static_cast<size_t>(id)] = t.value("task", "");
    }
  return tasks;
}

std::vector<LeRobotDataset::Episode> read_episodes_v2(const fs::path& root, const PathTemplates& paths,
                                                      const std::string& camera, const std::string& where) {
  using Episode = LeRobotDataset::Episode;
  std::vector<Episode> episodes;
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
        {"episode_chunk", ep.index / std::max<int64_t>(1, paths.chunks_size)}, {"episode_index", ep.index}};
    ep.data_file = root / format_path_template(paths.data, {}, numbers, where);
    ep.video_file = root / format_path_template(paths.video, {{"video_key", camera}}, numbers, where);
    episodes.push_back(std::move(ep));
  }
  return episodes;
}

// v2.1: per-episode stats; pooled here (min of mins, max of maxes, count-weighted moments).
std::map<std::string, ArrayStats> pool_episode_stats(const fs::path& episode_stats_path) {
  std::map<std::string, ArrayStats> column_stats;
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
  return column_stats;
}

}  // namespace dojo::data
