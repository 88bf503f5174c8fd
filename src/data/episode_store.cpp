#include "data/episode_store.h"

#include "data/episode_source.h"

#include <torch/torch.h>

#include <unistd.h>
#include <algorithm>

#include <fstream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/safetensors.h"
#include "io/video.h"

namespace fs = std::filesystem;

namespace dojo::data {

std::string to_string(Embodiment embodiment) { return embodiment == Embodiment::kHuman ? "human" : "robot"; }

Embodiment embodiment_from_string(const std::string& name, const std::string& where) {
  if (name == "human") return Embodiment::kHuman;
  if (name == "robot") return Embodiment::kRobot;
  throw Error(where + ": unknown embodiment '" + name + "' (expected human or robot)");
}

std::string to_string(VideoFormat format) { return format == VideoFormat::kRaw ? "raw" : "mp4"; }

VideoFormat video_format_from_string(const std::string& name, const std::string& where) {
  if (name == "mp4") return VideoFormat::kMp4;
  if (name == "raw") return VideoFormat::kRaw;
  throw Error(where + ": unknown video format '" + name + "' (expected mp4 or raw)");
}

namespace {

const char* video_extension(VideoFormat format) {
  return format == VideoFormat::kRaw ? ".safetensors" : ".mp4";
}

bool is_raw_video(const fs::path& file) { return file.extension() == ".safetensors"; }

// A raw video file, mapped (its frames: raw_frames).
SafetensorsFile open_raw_video(const fs::path& path) {
  if (!fs::exists(path)) throw Error(path.string() + ": missing");
  return SafetensorsFile::open(path);
}

// The frames of a raw video file, a view of its mapping (valid while `file` lives).
at::Tensor raw_frames(const SafetensorsFile& file, const fs::path& path) {
  DOJO_CHECK(file.contains("frames"), path.string() + ": no tensor 'frames'");
  auto frames = file.tensor("frames");
  DOJO_CHECK(frames.dim() == 4 && frames.size(3) == 3 && frames.scalar_type() == torch::kUInt8,
             path.string() + ": 'frames' must be [T, H, W, 3] uint8");
  return frames;
}

void check_finite(const at::Tensor& t, const std::string& what, const fs::path& where) {
  if (t.defined() && !torch::isfinite(t).all().item<bool>())
    throw Error(where.string() + ": " + what + " contains NaN or Inf");
}

}  // namespace

void write_episode(const fs::path& dir, const EpisodeData& episode, double fps, VideoFormat format) {
  DOJO_CHECK(episode.frames.defined() && episode.frames.dim() == 4 && episode.frames.size(3) == 3 &&
                 episode.frames.scalar_type() == torch::kUInt8,
             dir.string() + ": frames must be [T, H, W, 3] uint8");
  const int64_t t = episode.frames.size(0);
  auto check_rows = [&](const at::Tensor& a, const char* name) {
    if (a.defined())
      DOJO_CHECK(a.dim() == 2 && a.size(0) == t, dir.string() + ": " + name + " has " +
                                                     std::to_string(a.size(0)) + " rows for " +
                                                     std::to_string(t) + " frames");
  };
  check_rows(episode.actions, "action");
  check_rows(episode.states, "state");
  check_rows(episode.hidden_motion, "hidden_motion");
  check_rows(episode.keypoints, "keypoints");

  // Build the episode beside its final place, then rename: readers and a resumed generator
  // see either the whole episode or nothing.
  const fs::path tmp = dir.parent_path() / (dir.filename().string() + ".tmp-" + std::to_string(getpid()));
  fs::remove_all(tmp);
  fs::create_directories(tmp);
  {
    io::VideoWriterOptions options;
    options.fps = fps;
    // Episodes are small and decoded many times per epoch: a keyframe every 8 frames keeps
    // random access cheap, and a high quality keeps the world model's targets clean.
    options.keyframe_interval = 8;
    options.crf = 15;
    const auto write = [&](const std::string& name, const at::Tensor& frames) {
      const auto file = tmp / (name + video_extension(format));
      if (format == VideoFormat::kRaw)
        save_safetensors(file, {{"frames", frames.contiguous()}});
      else
        io::write_video(file.string(), frames, options);
    };
    write("video", episode.frames);
    for (const auto& [camera, frames] : episode.views) {
      DOJO_CHECK(
          frames.dim() == 4 && frames.size(0) == t && frames.scalar_type() == torch::kUInt8,
          dir.string() + ": camera '" + camera + "' needs [T, H, W, 3] uint8 frames, T as the main video");
      DOJO_CHECK(!camera.empty() && camera != "video" && camera.find('/') == std::string::npos,
                 dir.string() + ": bad camera name '" + camera + "'");
      write(camera, frames);
    }
  }
  NamedTensors arrays;
  if (episode.actions.defined())
    arrays.emplace_back("action", episode.actions.to(torch::kFloat32).contiguous());
  if (episode.states.defined()) arrays.emplace_back("state", episode.states.to(torch::kFloat32).contiguous());
  if (episode.hidden_motion.defined())
    arrays.emplace_back("hidden_motion", episode.hidden_motion.to(torch::kFloat32).contiguous());
  if (episode.keypoints.defined())
    arrays.emplace_back("keypoints", episode.keypoints.to(torch::kFloat32).contiguous());
  Metadata metadata;
  metadata["frames"] = std::to_string(t);
  save_safetensors(tmp / "data.safetensors", arrays, metadata);
  nlohmann::json meta = episode.meta;
  meta["frames"] = t;
  meta["height"] = episode.frames.size(1);
  meta["width"] = episode.frames.size(2);
  meta["fps"] = fps;
  write_file_atomic(tmp / "meta.json", meta.dump(2) + "\n");
  fsync_directory(tmp);
  fs::remove_all(dir);
  fs::rename(tmp, dir);
  fsync_directory(dir.parent_path());
}

int64_t DatasetInfo::total_frames() const {
  int64_t total = 0;
  for (const auto& e : episodes) total += e.frames;
  return total;
}

std::map<std::string, int64_t> DatasetInfo::split_counts() const {
  std::map<std::string, int64_t> counts;
  for (const auto& e : episodes) ++counts[e.split];
  return counts;
}

nlohmann::json DatasetInfo::to_json() const {
  nlohmann::json j;
  j["format"] = "dojo-episodes";
  j["format_version"] = 1;
  j["name"] = name;
  j["embodiment"] = to_string(embodiment);
  j["action_slot"] = action_slot;
  j["fps"] = fps;
  j["height"] = height;
  j["width"] = width;
  j["action_dim"] = action_dim;
  j["state_dim"] = state_dim;
  j["action_names"] = action_names;
  j["state_names"] = state_names;
  if (!keypoint_names.empty()) j["keypoint_names"] = keypoint_names;
  if (!cameras.empty()) j["cameras"] = cameras;
  if (video_format != VideoFormat::kMp4) j["video_format"] = data::to_string(video_format);
  j["num_episodes"] = episodes.size();
  j["num_frames"] = total_frames();
  j["splits"] = split_counts();
  nlohmann::json stats = nlohmann::json::object();
  if (action_stats) stats["action"] = action_stats->to_json();
  if (state_stats) stats["state"] = state_stats->to_json();
  j["stats"] = stats;
  j["generator"] = generator;
  j["episodes"] = nlohmann::json::array();
  for (const auto& e : episodes)
    j["episodes"].push_back({{"id", e.id}, {"frames", e.frames}, {"split", e.split}, {"task", e.task}});
  return j;
}

DatasetInfo DatasetInfo::from_json(const nlohmann::json& j, const std::string& where) {
  DatasetInfo info;
  try {
    if (j.value("format", "") != "dojo-episodes")
      throw Error(where + ": field 'format' must be \"dojo-episodes\"");
    info.name = j.value("name", "");
    info.embodiment =
        embodiment_from_string(j.at("embodiment").get<std::string>(), where + ": field 'embodiment'");
    info.action_slot = j.value("action_slot", "");
    if (!info.action_slot.empty()) (void)slot_by_name(info.action_slot);
    info.fps = j.at("fps").get<double>();
    info.height = j.value("height", 0);
    info.width = j.value("width", 0);
    info.action_dim = j.value("action_dim", 0);
    info.state_dim = j.value("state_dim", 0);
    info.action_names = j.value("action_names", std::vector<std::string>{});
    info.state_names = j.value("state_names", std::vector<std::string>{});
    info.keypoint_names = j.value("keypoint_names", std::vector<std::string>{});
    info.cameras = j.value("cameras", std::vector<std::string>{});
    info.video_format = video_format_from_string(j.value("video_format", std::string("mp4")),
                                                 where + ": field 'video_format'");
    if (j.contains("stats")) {
      const auto& stats = j.at("stats");
      if (stats.contains("action"))
        info.action_stats = ArrayStats::from_json(stats.at("action"), where + ": stats.action");
      if (stats.contains("state"))
        info.state_stats = ArrayStats::from_json(stats.at("state"), where + ": stats.state");
    }
    info.generator = j.value("generator", nlohmann::json::object());
    for (const auto& e : j.at("episodes")) {
      EpisodeEntry entry;
      entry.id = e.at("id").get<std::string>();
      entry.frames = e.at("frames").get<int64_t>();
      entry.split = e.value("split", "train");
      entry.task = e.value("task", "");
      info.episodes.push_back(entry);
    }
  } catch (const nlohmann::json::exception& e) {
    throw Error(where + ": " + e.what());
  }
  if (info.action_stats && info.action_stats->dim() != info.action_dim)
    throw Error(where + ": stats.action width " + std::to_string(info.action_stats->dim()) +
                " != action_dim " + std::to_string(info.action_dim));
  return info;
}

void write_preview_video(const EpisodeStore& store, const fs::path& out, size_t count, int scale) {
  write_preview_video(EpisodeStoreSource(store), out, count, scale);
}

void write_dataset_info(const fs::path& dir, const DatasetInfo& info) {
  write_file_atomic(dir / "info.json", info.to_json().dump(2) + "\n");
}

EpisodeStore EpisodeStore::open(const fs::path& dir) {
  const fs::path info_path = dir / "info.json";
  if (!fs::exists(info_path)) throw Error(dir.string() + ": not a dataset (no info.json)");
  EpisodeStore store;
  store.dir_ = dir;
  store.info_ = DatasetInfo::from_json(read_json_file(info_path), info_path.string());
  return store;
}

fs::path EpisodeStore::episode_dir(size_t index) const {
  DOJO_CHECK(index < size(), dir_.string() + ": episode index " + std::to_string(index) + " out of range");
  return dir_ / "episodes" / info_.episodes[index].id;
}

fs::path EpisodeStore::video_path(size_t index, const std::string& camera) const {
  const auto& cameras = info_.cameras;
  if (camera.empty() || (!cameras.empty() && camera == cameras.front()))
    return episode_dir(index) / (std::string("video") + video_extension(info_.video_format));
  if (std::find(cameras.begin() + (cameras.empty() ? 0 : 1), cameras.end(), camera) == cameras.end()) {
    std::string known;
    for (const auto& c : cameras) known += (known.empty() ? "" : ", ") + c;
    throw Error(dir_.string() + ": no camera '" + camera + "' (" +
                (known.empty() ? std::string("one camera recorded") : "cameras: " + known) + ")");
  }
  return episode_dir(index) / (camera + video_extension(info_.video_format));
}

std::vector<size_t> EpisodeStore::split_indices(const std::string& split) const {
  std::vector<size_t> out;
  for (size_t i = 0; i < size(); ++i)
    if (split.empty() || split == "all" || info_.episodes[i].split == split) out.push_back(i);
  return out;
}

EpisodeData EpisodeStore::load_arrays(size_t index) const {
  const fs::path edir = episode_dir(index);
  const int64_t frames = info_.episodes[index].frames;
  EpisodeData data;
  if (!fs::exists(edir)) throw Error(edir.string() + ": episode directory missing");
  data.meta = read_json_file(edir / "meta.json");
  const fs::path arrays_path = edir / "data.safetensors";
  if (!fs::exists(arrays_path)) throw Error(arrays_path.string() + ": missing");
  const auto file = SafetensorsFile::open(arrays_path);
  auto take = [&](const char* name, int64_t width) -> at::Tensor {
    if (!file.contains(name)) {
      if (width > 0) throw Error(arrays_path.string() + ": tensor '" + name + "' missing");
      return {};
    }
    auto t = file.tensor(name, /*copy=*/true).to(torch::kFloat32);
    if (t.dim() != 2 || t.size(0) != frames)
      throw Error(arrays_path.string() + ": '" + name + "' has " + std::to_string(t.dim() ? t.size(0) : 0) +
                  " rows but the episode has " + std::to_string(frames) + " frames");
    if (width > 0 && t.size(1) != width)
      throw Error(arrays_path.string() + ": '" + name + "' width " + std::to_string(t.size(1)) +
                  " != dataset width " + std::to_string(width));
    check_finite(t, std::string("'") + name + "'", arrays_path);
    return t;
  };
  data.actions = take("action", info_.embodiment == Embodiment::kRobot ? info_.action_dim : 0);
  data.states = take("state", info_.embodiment == Embodiment::kRobot ? info_.state_dim : 0);
  data.hidden_motion = take("hidden_motion", 0);
  data.keypoints = take("keypoints", 0);
  if (data.keypoints.defined() &&
      data.keypoints.size(1) != 3 * static_cast<int64_t>(info_.keypoint_names.size()))
    throw Error(arrays_path.string() + ": 'keypoints' width " + std::to_string(data.keypoints.size(1)) +
                " is not 3 x the " + std::to_string(info_.keypoint_names.size()) +
                " keypoint_names of info.json");
  return data;
}

EpisodeData EpisodeStore::load(size_t index) const {
  EpisodeData data = load_arrays(index);
  data.frames = read_all_video_frames(video_path(index), info_.episodes[index].frames);
  return data;
}

std::string EpisodeStore::check_episode(size_t index) const {
  try {
    (void)load(index);
    return "";
  } catch (const std::exception& e) {
    return e.what();
  }
}

at::Tensor read_video_frames(const fs::path& file, const std::vector<int64_t>& indices, int decoder_threads) {
  if (!is_raw_video(file)) {
    io::VideoReaderOptions options;
    options.threads = decoder_threads;
    io::VideoReader reader(file.string(), options);
    return reader.read_frames(indices);
  }
  const auto mapped = open_raw_video(file);
  const auto frames = raw_frames(mapped, file);  // [T, H, W, 3] u8
  for (int64_t i : indices)
    DOJO_CHECK(i >= 0 && i < frames.size(0), file.string() + ": frame " + std::to_string(i) +
                                                 " out of range (" + std::to_string(frames.size(0)) +
                                                 " frames)");
  return frames.index_select(0, torch::tensor(indices, torch::kLong));  // a copy: outlives the mapping
}

at::Tensor read_all_video_frames(const fs::path& file, int64_t expected) {
  int64_t found = 0;
  at::Tensor frames;
  if (is_raw_video(file)) {
    const auto mapped = open_raw_video(file);
    frames = raw_frames(mapped, file).clone();
    found = frames.size(0);
  } else {
    io::VideoReader reader(file.string());
    found = reader.info().frames;
    if (found == expected) frames = reader.read_range(0, expected, 1);
  }
  if (found != expected)
    throw Error(file.string() + ": video has " + std::to_string(found) + " frames, the dataset lists " +
                std::to_string(expected));
  return frames;
}

}  // namespace dojo::data
