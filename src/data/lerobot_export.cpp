#include "data/lerobot_export.h"

#include <torch/torch.h>

#include <algorithm>
#include <cstdio>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <set>
#include <sstream>
#include <vector>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/json_file.h"
#include "data/actions.h"
#include "io/frame_ops.h"
#include "io/parquet_writer.h"
#include "io/video.h"

namespace fs = std::filesystem;

namespace dojo::data {
namespace {

constexpr int64_t kChunkSize = 1000;  // episodes per chunk directory, as LeRobot writes

// Source episode indices split by split: train, val, test, then the others by first appearance.
std::vector<std::pair<std::string, std::vector<size_t>>> episodes_by_split(const DatasetInfo& info,
                                                                           size_t count) {
  std::vector<std::pair<std::string, std::vector<size_t>>> groups;
  for (const char* name : {"train", "val", "test"}) groups.push_back({name, {}});
  for (size_t i = 0; i < count; ++i) {
    const auto& split = info.episodes[i].split;
    auto it = std::find_if(groups.begin(), groups.end(), [&](const auto& g) { return g.first == split; });
    if (it == groups.end()) it = groups.insert(groups.end(), {split, {}});
    it->second.push_back(i);
  }
  groups.erase(std::remove_if(groups.begin(), groups.end(), [](const auto& g) { return g.second.empty(); }),
               groups.end());
  return groups;
}

// One modality key per dimension, named after it where the dataset names its dimensions.
nlohmann::json modality_keys(const std::vector<std::string>& names, int64_t width,
                             const std::string& prefix) {
  nlohmann::json keys = nlohmann::json::object();
  const bool named = static_cast<int64_t>(names.size()) == width &&
                     std::set<std::string>(names.begin(), names.end()).size() == names.size();
  for (int64_t d = 0; d < width; ++d)
    keys[named ? names[static_cast<size_t>(d)] : prefix + "_" + std::to_string(d)] = {{"start", d},
                                                                                      {"end", d + 1}};
  return keys;
}

std::vector<std::optional<std::vector<float>>> rows_of(const at::Tensor& array) {  // [T, D] float
  const auto a = array.to(torch::kFloat32).contiguous();
  std::vector<std::optional<std::vector<float>>> rows;
  for (int64_t t = 0; t < a.size(0); ++t) {
    const float* p = a[t].data_ptr<float>();
    rows.push_back(std::vector<float>(p, p + a.size(1)));
  }
  return rows;
}

std::string numbered(const char* format, int64_t number) {
  char text[32];
  std::snprintf(text, sizeof text, format, static_cast<long long>(number));
  return text;
}

}  // namespace

ConvertResult export_lerobot(const EpisodeSource& source, const fs::path& dst,
                             const LeRobotExportOptions& options, const std::function<void()>& on_episode) {
  DOJO_CHECK(!options.robot_type.empty(),
             dst.string() + ": name the robot (--robot-type): LeRobot readers find it in info.json");
  DOJO_CHECK(!options.camera.empty() && options.camera.find('/') == std::string::npos,
             "lerobot export: --camera must be a plain name, got '" + options.camera + "'");
  DOJO_CHECK(fs::absolute(dst) != fs::absolute(source.root()),
             dst.string() + ": cannot export a dataset onto itself");
  const DatasetInfo& src = source.info();
  const nlohmann::json job = {{"source", fs::absolute(source.root()).string()},
                              {"format", source.format()},
                              {"robot_type", options.robot_type},
                              {"camera", options.camera},
                              {"height", options.height},
                              {"width", options.width},
                              {"limit", options.limit},
                              {"crf", options.crf}};
  const fs::path job_path = dst / "export.json";
  if (fs::exists(job_path)) {
    if (read_json_file(job_path) != job)
      throw Error(job_path.string() + ": this directory holds an export with other options; use another DST");
  } else {
    if (fs::exists(dst) && !fs::is_empty(dst))
      throw Error(dst.string() + ": exists and is not an export output");
    fs::create_directories(dst);
    write_file_atomic(job_path, job.dump(2) + "\n");
  }

  const size_t count =
      options.limit < 0 ? source.size() : std::min(source.size(), static_cast<size_t>(options.limit));
  // Every camera the source records: the main one under options.camera, the others (our format's
  // info.json cameras) under their own names.
  std::vector<std::pair<std::string, std::shared_ptr<const EpisodeSource>>> cameras = {
      {options.camera, std::shared_ptr<const EpisodeSource>(&source, [](const EpisodeSource*) {})}};
  if (source.format() == "dojo-episodes")
    for (size_t c = 1; c < source.info().cameras.size(); ++c) {
      OpenOptions one;
      one.camera = source.info().cameras[c];
      DOJO_CHECK(one.camera != options.camera, "lerobot export: --video-name '" + options.camera +
                                                   "' is also the name of another camera of the dataset");
      cameras.push_back({one.camera, open_dataset(source.root(), one)});
    }
  const std::string video_key = "observation.images." + options.camera;
  std::vector<std::string> tasks;
  std::ostringstream episodes_jsonl;
  nlohmann::json splits = nlohmann::json::object();
  StatsAccumulator action_acc, state_acc;
  int64_t action_width = 0, state_width = 0, total_frames = 0, height = 0, width = 0, index = 0;
  ConvertResult result;
  io::VideoWriterOptions video_options;
  video_options.fps = src.fps;
  video_options.crf = options.crf;
  for (const auto& [split, members] : episodes_by_split(src, count)) {
    splits[split] =
        std::to_string(index) + ":" + std::to_string(index + static_cast<int64_t>(members.size()));
    for (const size_t i : members) {
      const EpisodeEntry& entry = src.episodes[i];
      const auto name = numbered("episode_%06lld", index);
      const auto chunk = numbered("chunk-%03lld", index / kChunkSize);
      const fs::path table = dst / "data" / chunk / (name + ".parquet");
      const fs::path video = dst / "videos" / chunk / video_key / (name + ".mp4");
      const EpisodeData arrays = source.read_arrays(i);
      const int64_t frames = entry.frames;
      if (arrays.actions.defined()) {
        DOJO_CHECK(arrays.actions.size(0) == frames,
                   source.episode_location(i) + ": " + std::to_string(arrays.actions.size(0)) +
                       " action rows for " + std::to_string(frames) + " frames");
        action_width = arrays.actions.size(1);
        action_acc.add(arrays.actions.to(torch::kFloat32));
      }
      if (arrays.states.defined()) {
        state_width = arrays.states.size(1);
        state_acc.add(arrays.states.to(torch::kFloat32));
      }
      auto task = std::find(tasks.begin(), tasks.end(), entry.task);
      if (task == tasks.end()) task = tasks.insert(tasks.end(), entry.task);
      const int64_t task_index = task - tasks.begin();
      if (fs::exists(table) && fs::exists(video)) {
        ++result.kept;
      } else {
        io::ParquetWriter w;
        std::vector<float> timestamp;
        std::vector<int64_t> frame_index, episode_index, global_index, task_indices;
        for (int64_t k = 0; k < frames; ++k) {
          timestamp.push_back(static_cast<float>(static_cast<double>(k) / src.fps));
          frame_index.push_back(k);
          episode_index.push_back(index);
          global_index.push_back(total_frames + k);
          task_indices.push_back(task_index);
        }
        if (arrays.states.defined()) w.add_list_f32("observation.state", rows_of(arrays.states));
        if (arrays.actions.defined()) w.add_list_f32("action", rows_of(arrays.actions));
        w.add_f32("timestamp", timestamp);
        w.add_i64("frame_index", frame_index);
        w.add_i64("episode_index", episode_index);
        w.add_i64("index", global_index);
        w.add_i64("task_index", task_indices);
        std::vector<int64_t> all(static_cast<size_t>(frames));
        for (int64_t f = 0; f < frames; ++f) all[static_cast<size_t>(f)] = f;
        // The videos first, the table last: a table on disk means its episode is complete.
        for (const auto& [camera, camera_source] : cameras) {
          auto pixels = camera_source->read_frames(i, all);  // [T, H, W, 3] u8
          if (options.height > 0 && options.width > 0)
            pixels = io::resize_center_crop(pixels, options.height, options.width);
          const fs::path file = dst / "videos" / chunk / ("observation.images." + camera) / (name + ".mp4");
          fs::create_directories(file.parent_path());
          const fs::path partial = file.parent_path() / ("." + name + ".partial.mp4");
          io::write_video(partial.string(), pixels, video_options);
          fs::rename(partial, file);
        }
        fs::create_directories(table.parent_path());
        write_file_atomic(table, w.to_bytes());
        ++result.converted;
      }
      if (height == 0) {
        const auto first = source.read_frames(i, {0});
        height = options.height > 0 ? options.height : first.size(1);
        width = options.width > 0 ? options.width : first.size(2);
      }
      episodes_jsonl
          << nlohmann::json{{"episode_index", index}, {"tasks", {entry.task}}, {"length", frames}}.dump()
          << "\n";
      total_frames += frames;
      ++index;
      if (on_episode) on_episode();
    }
  }
  DOJO_CHECK(index > 0, source.root().string() + ": no episodes to export");

  // meta/, last.
  nlohmann::json features = nlohmann::json::object();
  nlohmann::json modality = {{"video", nlohmann::json::object()}};
  for (const auto& [camera, unused] : cameras) {
    const std::string key = "observation.images." + camera;
    modality["video"][camera] = {{"original_key", key}};
    features[key] = {{"dtype", "video"},
                     {"shape", {height, width, 3}},
                     {"names", {"height", "width", "channel"}},
                     {"info",
                      {{"video.height", height},
                       {"video.width", width},
                       {"video.codec", "h264"},
                       {"video.pix_fmt", "yuv420p"},
                       {"video.fps", src.fps},
                       {"video.channels", 3}}}};
  }
  nlohmann::json stats = nlohmann::json::object();
  if (state_width > 0) {
    features["observation.state"] = {
        {"dtype", "float32"}, {"shape", {state_width}}, {"names", src.state_names}};
    modality["state"] = modality_keys(src.state_names, state_width, "state");
    stats["observation.state"] = state_acc.finish().to_json();
  }
  if (action_width > 0) {
    features["action"] = {{"dtype", "float32"}, {"shape", {action_width}}, {"names", src.action_names}};
    modality["action"] = modality_keys(src.action_names, action_width, "action");
    stats["action"] = action_acc.finish().to_json();
  }
  for (const char* column : {"timestamp"}) features[column] = {{"dtype", "float32"}, {"shape", {1}}};
  for (const char* column : {"frame_index", "episode_index", "index", "task_index"})
    features[column] = {{"dtype", "int64"}, {"shape", {1}}};
  const nlohmann::json info = {
      {"codebase_version", "v2.1"},
      {"robot_type", options.robot_type},
      {"fps", src.fps},
      {"total_episodes", index},
      {"total_frames", total_frames},
      {"total_tasks", tasks.size()},
      {"total_videos", index * static_cast<int64_t>(cameras.size())},
      {"total_chunks", (index + kChunkSize - 1) / kChunkSize},
      {"chunks_size", kChunkSize},
      {"splits", splits},
      {"data_path", "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"},
      {"video_path", "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"},
      {"features", features}};
  std::ostringstream tasks_jsonl;
  for (size_t t = 0; t < tasks.size(); ++t)
    tasks_jsonl << nlohmann::json{{"task_index", t}, {"task", tasks[t]}}.dump() << "\n";
  const fs::path meta = dst / "meta";
  fs::create_directories(meta);
  write_file_atomic(meta / "tasks.jsonl", tasks_jsonl.str());
  write_file_atomic(meta / "episodes.jsonl", episodes_jsonl.str());
  write_file_atomic(meta / "stats.json", stats.dump(2) + "\n");
  write_file_atomic(meta / "modality.json", modality.dump(2) + "\n");
  write_file_atomic(meta / "info.json", info.dump(2) + "\n");  // last: the dataset's mark of completeness
  return result;
}

}  // namespace dojo::data
