// Internal to src/data: what the LeRobot reader's files share. lerobot_open.cpp opens a dataset
// (LeRobotDataset::open and its steps); lerobot_v2.cpp and lerobot_v3.cpp read the task and
// episode tables of each version; lerobot.cpp reads episodes.
#pragma once

#include <cstdint>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "data/lerobot.h"

namespace dojo::data {

// Statistics {min, max[, mean, std]} of one column (mean defaults to min, std to 0). Throws
// dojo::Error "WHERE: ..." on bad fields or lengths. Defined in lerobot_open.cpp.
ArrayStats stats_from_json(const nlohmann::json& j, const std::string& where);

// info.json's data_path and video_path templates (or the version's defaults) and chunks_size.
struct PathTemplates {
  int64_t chunks_size = 1000;
  std::string data, video;
};

// v2.x (lerobot_v2.cpp): meta/tasks.jsonl (texts by task_index; empty without the file) and
// meta/episodes.jsonl (one file per episode, paths from the templates for `camera`).
// `where` names info.json in template errors.
std::vector<std::string> read_tasks_v2(const std::filesystem::path& root);
std::vector<LeRobotDataset::Episode> read_episodes_v2(const std::filesystem::path& root,
                                                      const PathTemplates& paths, const std::string& camera,
                                                      const std::string& where);
// v2.1's meta/episodes_stats.jsonl: the action and observation.state stats of every episode
// pooled into one ArrayStats per column.
std::map<std::string, ArrayStats> pool_episode_stats(const std::filesystem::path& path);

// v3.0 (lerobot_v3.cpp): meta/tasks.parquet and meta/episodes/**/*.parquet (episodes sharing
// chunked data and video files, each with its span in the video).
std::vector<std::string> read_tasks_v3(const std::filesystem::path& root);
std::vector<LeRobotDataset::Episode> read_episodes_v3(const std::filesystem::path& root,
                                                      const PathTemplates& paths, const std::string& camera,
                                                      const std::string& where);

}  // namespace dojo::data
