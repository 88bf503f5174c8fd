// LeRobot v3.0 tables: meta/tasks.parquet and the episode table meta/episodes/**/*.parquet
// (one row per episode; episodes share chunked data and video files).
#include <algorithm>
#include <string>
#include <utility>
#include <vector>

#include "core/error.h"
#include "data/lerobot.h"
#include "data/lerobot_internal.h"
#include "io/parquet.h"

namespace fs = std::filesystem;

namespace dojo::data {

std::vector<std::string> read_tasks_v3(const fs::path& root) {
  std::vector<std::string> tasks;
  const fs::path tasks_path = root / "meta" / "tasks.parquet";
  if (fs::exists(tasks_path)) {
    const auto file = io::ParquetFile::open(tasks_path);
    const auto ids = file.read_i64("task_index");
    std::string text_column = file.has_column("task") ? "task" : "__index_level_0__";
    const auto texts = file.read_string(text_column);
    for (size_t i = 0; i < ids.size(); ++i) {
      if (ids[i] < 0 || ids[i] > 1000000) throw Error(tasks_path.string() + ": task_index out of range");
      if (static_cast<size_t>(ids[i]) >= tasks.size()) tasks.resize(static_cast<size_t>(ids[i]) + 1);
      tasks[static_cast<size_t>(ids[i])] = texts[i];
    }
  }
  return tasks;
}

std::vector<LeRobotDataset::Episode> read_episodes_v3(const fs::path& root, const PathTemplates& paths,
                                                      const std::string& camera, const std::string& where) {
  using Episode = LeRobotDataset::Episode;
  std::vector<Episode> episodes;
  std::vector<fs::path> files;
  const fs::path dir = root / "meta" / "episodes";
  if (!fs::exists(dir)) throw Error(dir.string() + ": missing (LeRobot v3.0 episode table)");
  for (const auto& e : fs::recursive_directory_iterator(dir))
    if (e.is_regular_file() && e.path().extension() == ".parquet") files.push_back(e.path());
  std::sort(files.begin(), files.end());
  if (files.empty()) throw Error(dir.string() + ": no episode parquet files");
  const std::string vk = "videos/" + camera + "/";
  for (const auto& path : files) {
    const auto file = io::ParquetFile::open(path);
    const auto index = file.read_i64("episode_index");
    const auto length = file.read_i64("length");
    const auto data_chunk = file.read_i64("data/chunk_index");
    const auto data_file = file.read_i64("data/file_index");
    if (!file.has_column(vk + "chunk_index"))
      throw Error(path.string() + ": no column '" + vk + "chunk_index' for camera '" + camera + "'");
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
        ep.tasks.assign(tasks.values.begin() + tasks.offsets[i], tasks.values.begin() + tasks.offsets[i + 1]);
      ep.data_file =
          root / format_path_template(paths.data, {},
                                      {{"chunk_index", data_chunk[i]}, {"file_index", data_file[i]}}, where);
      ep.video_file = root / format_path_template(
                                 paths.video, {{"video_key", camera}},
                                 {{"chunk_index", video_chunk[i]}, {"file_index", video_file[i]}}, where);
      ep.from_timestamp = from[i];
      ep.to_timestamp = to[i];
      episodes.push_back(std::move(ep));
    }
  }
  return episodes;
}

}  // namespace dojo::data
