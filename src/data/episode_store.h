// The episode dataset format of DojoSim (and of any data converted to it):
//
//   DIR/info.json                     dataset description, per-dimension statistics, splits
//   DIR/episodes/000042/video.mp4     H.264 frames (the first camera of info.json's "cameras")
//   DIR/episodes/000042/<camera>.mp4  the other cameras' frames, when the dataset records several
//                                     (info.json "video_format": "raw": video.safetensors and
//                                     <camera>.safetensors, the frames themselves, see VideoFormat)
//   DIR/episodes/000042/data.safetensors  "action" [T, A] f32, "state" [T, S] f32,
//                                     "hidden_motion" [T, M] f32 (optional; evaluation only),
//                                     "keypoints" [T, 3K] f32 (optional; simulator ground truth:
//                                     u, v, in_view per keypoint, u and v normalised to the image)
//   DIR/episodes/000042/meta.json     embodiment, task text, objects, background, fps, seed
//
// T frames, T actions, T states: action[t] is the command issued after observing frame t.
// An episode directory appears only when complete (written as a sibling temp dir, renamed),
// so an interrupted generator leaves either a whole episode or none.
#pragma once

#include <ATen/core/Tensor.h>

#include <filesystem>
#include <map>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "data/actions.h"

namespace dojo::data {

enum class Embodiment { kHuman, kRobot };
std::string to_string(Embodiment embodiment);
// Throws dojo::Error naming `where` for an unknown name.
Embodiment embodiment_from_string(const std::string& name, const std::string& where);

// How episodes store their frames: H.264 in .mp4 files (the default: about a tenth of the size),
// or raw, the uint8 frames in .safetensors files ("frames" [T, H, W, 3]), which need no video
// library to read or write: a build without FFmpeg (DOJO_WITH_MEDIA=OFF, e.g. trainers on a GPU
// machine) reads and writes only those.
enum class VideoFormat { kMp4, kRaw };
std::string to_string(VideoFormat format);  // "mp4" | "raw"
// Throws dojo::Error naming `where` for an unknown name.
VideoFormat video_format_from_string(const std::string& name, const std::string& where);
// Frames `indices` (in the order given, duplicates allowed) of an episode video file of either
// format, told apart by its extension: [N, H, W, 3] uint8. Errors name the file and the index.
at::Tensor read_video_frames(const std::filesystem::path& file, const std::vector<int64_t>& indices,
                             int decoder_threads = 0);
// Every frame of such a file, checked to be `expected` of them (the dataset's count).
at::Tensor read_all_video_frames(const std::filesystem::path& file, int64_t expected);

// What an episode holds in memory, before writing or after reading.
struct EpisodeData {
  at::Tensor frames;         // [T, H, W, 3] uint8
  at::Tensor actions;        // [T, A] float32, or undefined for action-free (human) video
  at::Tensor states;         // [T, S] float32, or undefined
  at::Tensor hidden_motion;  // [T, M] float32, or undefined: ground truth never used for training
  // [T, 3K] float32 (u, v, in_view) per keypoint of the embodiment, (u, v) in [0, 1] over the
  // image; evaluation and pose probes only, never a world-model input. Undefined when unknown.
  at::Tensor keypoints;
  nlohmann::json meta = nlohmann::json::object();
  // Other cameras' frames [T, H, W, 3] u8, written as <camera>.mp4 beside video.mp4.
  std::vector<std::pair<std::string, at::Tensor>> views;
};

// Writes one episode directory atomically. `fps` goes into the video container.
void write_episode(const std::filesystem::path& dir, const EpisodeData& episode, double fps,
                   VideoFormat format = VideoFormat::kMp4);

// One row of info.json's episode table.
struct EpisodeEntry {
  std::string id;  // directory name under episodes/
  int64_t frames = 0;
  std::string split;  // "train", "val", "ood_objects", ...
  std::string task;
};

struct DatasetInfo {
  std::string name;
  Embodiment embodiment = Embodiment::kRobot;
  std::string action_slot;  // slot name for robot actions, e.g. "dojosim_robot"; empty for human
  double fps = 10;
  int height = 0, width = 0;
  int action_dim = 0, state_dim = 0;
  std::vector<std::string> action_names, state_names;
  std::vector<std::string> keypoint_names;  // the K keypoints of EpisodeData::keypoints, if any
  // Cameras recorded, the main one (video.mp4) first; empty: one camera. Keypoints are the
  // main camera's.
  std::vector<std::string> cameras;
  VideoFormat video_format = VideoFormat::kMp4;  // info.json "video_format" (absent: mp4)
  std::optional<ArrayStats> action_stats, state_stats;
  std::vector<EpisodeEntry> episodes;
  nlohmann::json generator = nlohmann::json::object();  // how the data was made (seed, options)

  int64_t total_frames() const;
  std::map<std::string, int64_t> split_counts() const;
  nlohmann::json to_json() const;
  static DatasetInfo from_json(const nlohmann::json& j, const std::string& where);
};

// Reads and validates a dataset directory. Episode data is loaded lazily.
class EpisodeStore {
 public:
  // Throws dojo::Error naming the file for a missing or malformed info.json.
  static EpisodeStore open(const std::filesystem::path& dir);

  const std::filesystem::path& dir() const { return dir_; }
  const DatasetInfo& info() const { return info_; }
  size_t size() const { return info_.episodes.size(); }
  std::filesystem::path episode_dir(size_t index) const;
  // The video of `camera` (one of info().cameras; "" or the first: video.mp4). Throws dojo::Error
  // naming the dataset and its cameras for another name.
  std::filesystem::path video_path(size_t index, const std::string& camera = "") const;

  // Episode indices whose split is `split` ("" or "all" = every episode).
  std::vector<size_t> split_indices(const std::string& split) const;

  // Arrays and meta of one episode (no frames). Validates lengths against the frame count
  // and rejects NaN/Inf; errors name the episode directory.
  EpisodeData load_arrays(size_t index) const;
  // Arrays plus every decoded frame.
  EpisodeData load(size_t index) const;

  // Full check of one episode (files present, arrays consistent, video decodable with the
  // recorded frame count). Returns an empty string when fine, else the one-line problem.
  std::string check_episode(size_t index) const;

 private:
  std::filesystem::path dir_;
  DatasetInfo info_;
};

// Writes the first `count` episodes side by side into one mp4, each labelled with its task,
// frames upscaled `scale` times (nearest neighbour) so small renders stay legible.
void write_preview_video(const EpisodeStore& store, const std::filesystem::path& out, size_t count,
                         int scale);

// Writes info.json atomically.
void write_dataset_info(const std::filesystem::path& dir, const DatasetInfo& info);

}  // namespace dojo::data
