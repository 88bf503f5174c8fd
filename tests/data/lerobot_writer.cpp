#include "lerobot_writer.h"

#include <torch/torch.h>

#include <cstdio>
#include <fstream>

#include "io/video.h"

namespace fs = std::filesystem;

namespace dojo::data::lerobot_fixture {

const char* const kCamera = "observation.images.ego_view_freq20";

float raw_action(int episode, int64_t row, int dim) { return 100.f * episode + row + 0.01f * dim; }
int level(int64_t g) { return 10 + 4 * static_cast<int>(g); }

at::Tensor grey_frames(int64_t first, int64_t count) {
  auto levels = (torch::arange(first, first + count) * 4 + 10).to(torch::kUInt8);  // [T]
  return levels.view({count, 1, 1, 1}).expand({count, 32, 32, 3}).contiguous();    // [T, 32, 32, 3]
}

void write_json(const fs::path& path, const nlohmann::json& j) {
  fs::create_directories(path.parent_path());
  std::ofstream(path) << j.dump(2);
}

nlohmann::json gr1_modality() {
  nlohmann::json m;
  const std::vector<std::pair<std::string, std::pair<int, int>>> keys = {
      {"left_arm", {0, 7}},    {"left_hand", {7, 13}},   {"left_leg", {13, 19}},  {"neck", {19, 22}},
      {"right_arm", {22, 29}}, {"right_hand", {29, 35}}, {"right_leg", {35, 41}}, {"waist", {41, 44}}};
  for (const auto& [key, range] : keys) {
    m["state"][key] = {{"start", range.first}, {"end", range.second}};
    m["action"][key] = {{"start", range.first}, {"end", range.second}, {"absolute", true}};
  }
  m["video"]["ego_view_freq20"] = {{"original_key", kCamera}};
  m["annotation"]["human.action.task_description"] = nlohmann::json::object();
  return m;
}

// Rows of episodes [first, last) as a parquet table.
io::ParquetWriter data_table(const Fixture& fx, int first, int last, const io::ParquetWriteOptions& options) {
  io::ParquetWriter w(options);
  std::vector<std::optional<std::vector<float>>> action, state;
  std::vector<float> timestamp;
  std::vector<int64_t> frame_index, episode_index, index, task_index;
  for (int e = first; e < last; ++e)
    for (int64_t k = 0; k < fx.frames; ++k) {
      std::vector<float> a(fx.raw_dim);
      for (int d = 0; d < fx.raw_dim; ++d) a[d] = raw_action(e, k, d);
      std::vector<float> s = a;
      for (float& v : s) v -= 1;
      action.push_back(a);
      state.push_back(s);
      timestamp.push_back(static_cast<float>(k / kFps));
      frame_index.push_back(k);
      episode_index.push_back(e);
      index.push_back(e * fx.frames + k);
      task_index.push_back(e % 2);
    }
  w.add_list_f32("observation.state", state);
  w.add_list_f32("action", action);
  w.add_f32("timestamp", timestamp);
  w.add_i64("frame_index", frame_index);
  w.add_i64("episode_index", episode_index);
  w.add_i64("index", index);
  w.add_i64("task_index", task_index);
  return w;
}

const std::vector<std::string> kTasks = {"pick up the cup", "wave"};

fs::path make_lerobot(const fs::path& root, const Fixture& fx) {
  nlohmann::json info;
  info["codebase_version"] = fx.v3 ? "v3.0" : "v2.1";
  info["robot_type"] = fx.robot_type;
  info["fps"] = kFps;
  info["total_episodes"] = fx.episodes;
  info["total_frames"] = fx.episodes * fx.frames;
  info["chunks_size"] = 1000;
  info["splits"] = {{"train", "0:" + std::to_string(fx.episodes)}};
  info["data_path"] = fx.v3 ? "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
                            : "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet";
  info["video_path"] = fx.v3 ? "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
                             : "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4";
  info["features"][kCamera] = {
      {"dtype", "video"},
      {"shape", {32, 32, 3}},
      {"names", {"height", "width", "channel"}},
      {"info", {{"video.height", 32}, {"video.width", 32}, {"video.codec", "h264"}, {"video.fps", kFps}}}};
  info["features"]["observation.state"] = {{"dtype", "float32"}, {"shape", {fx.raw_dim}}};
  info["features"]["action"] = {{"dtype", "float32"}, {"shape", {fx.raw_dim}}};
  info["features"]["timestamp"] = {{"dtype", "float32"}, {"shape", {1}}};
  write_json(root / "meta" / "info.json", info);
  if (fx.modality) write_json(root / "meta" / "modality.json", gr1_modality());
  nlohmann::json stats;
  std::vector<float> mn(fx.raw_dim), mx(fx.raw_dim), mean(fx.raw_dim), sd(fx.raw_dim, 1.f);
  for (int d = 0; d < fx.raw_dim; ++d) {
    mn[d] = raw_action(0, 0, d);
    mx[d] = raw_action(fx.episodes - 1, fx.frames - 1, d);
    mean[d] = (mn[d] + mx[d]) / 2;
  }
  stats["action"] = {{"min", mn}, {"max", mx}, {"mean", mean}, {"std", sd}};
  write_json(root / "meta" / "stats.json", stats);

  io::VideoWriterOptions vopt;
  vopt.fps = kFps;
  vopt.keyframe_interval = 8;
  vopt.crf = 10;
  if (!fx.v3) {
    std::ofstream episodes(root / "meta" / "episodes.jsonl"), tasks(root / "meta" / "tasks.jsonl");
    for (size_t t = 0; t < kTasks.size(); ++t)
      tasks << nlohmann::json{{"task_index", t}, {"task", kTasks[t]}}.dump() << "\n";
    io::ParquetWriteOptions popt;
    popt.codec = io::ParquetCodec::kSnappy;
    for (int e = 0; e < fx.episodes; ++e) {
      episodes
          << nlohmann::json{{"episode_index", e}, {"tasks", {kTasks[e % 2]}}, {"length", fx.frames}}.dump()
          << "\n";
      char name[64];
      std::snprintf(name, sizeof name, "episode_%06d", e);
      data_table(fx, e, e + 1, popt).write(root / "data" / "chunk-000" / (std::string(name) + ".parquet"));
      const fs::path video = root / "videos" / "chunk-000" / kCamera / (std::string(name) + ".mp4");
      fs::create_directories(video.parent_path());
      io::write_video(video.string(), grey_frames(e * fx.frames, fx.frames), vopt);
    }
  } else {
    io::ParquetWriteOptions popt;
    popt.codec = io::ParquetCodec::kZstd;
    popt.page_version = 2;
    popt.dictionary = true;
    popt.rows_per_page = 16;
    data_table(fx, 0, fx.episodes, popt).write(root / "data" / "chunk-000" / "file-000.parquet");
    const fs::path video = root / "videos" / kCamera / "chunk-000" / "file-000.mp4";
    fs::create_directories(video.parent_path());
    io::write_video(video.string(), grey_frames(0, fx.episodes * fx.frames), vopt);
    io::ParquetWriter ep(popt);
    std::vector<int64_t> index, length, zeros, from_index, to_index;
    std::vector<double> from_ts, to_ts;
    std::vector<std::vector<std::string>> tasks;
    for (int e = 0; e < fx.episodes; ++e) {
      index.push_back(e);
      length.push_back(fx.frames);
      zeros.push_back(0);
      from_index.push_back(e * fx.frames);
      to_index.push_back((e + 1) * fx.frames);
      from_ts.push_back(e * fx.frames / kFps);
      to_ts.push_back((e + 1) * fx.frames / kFps);
      tasks.push_back({kTasks[e % 2]});
    }
    const std::string vk = std::string("videos/") + kCamera + "/";
    ep.add_i64("episode_index", index);
    ep.add_list_string("tasks", tasks);
    ep.add_i64("length", length);
    ep.add_i64("data/chunk_index", zeros);
    ep.add_i64("data/file_index", zeros);
    ep.add_i64("dataset_from_index", from_index);
    ep.add_i64("dataset_to_index", to_index);
    ep.add_i64(vk + "chunk_index", zeros);
    ep.add_i64(vk + "file_index", zeros);
    ep.add_f64(vk + "from_timestamp", from_ts);
    ep.add_f64(vk + "to_timestamp", to_ts);
    ep.write(root / "meta" / "episodes" / "chunk-000" / "file-000.parquet");
    io::ParquetWriter tasks_table;
    tasks_table.add_string("task", kTasks);
    tasks_table.add_i64("task_index", {0, 1});
    tasks_table.write(root / "meta" / "tasks.parquet");
  }
  return root;
}

}  // namespace dojo::data::lerobot_fixture
