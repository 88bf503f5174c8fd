// Where the clip pipeline gets episodes from. Every dataset format is read through this one
// interface: our episode format (EpisodeStore), LeRobot v2.x / v3.0, EgoDex and plain video
// folders. A source describes itself with the same DatasetInfo as an episode store (episode
// table, fps, embodiment, action slot and statistics) and serves frames by index and per-frame
// arrays, so ClipDataset applies the same windows, crops and action transforms to all of them.
#pragma once

#include <ATen/core/Tensor.h>

#include <filesystem>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "data/episode_store.h"

namespace dojo::data {

class EpisodeSource {
 public:
  virtual ~EpisodeSource() = default;

  // "dojo-episodes", "lerobot-v2.1", "lerobot-v3.0", "egodex", "video-folder".
  virtual std::string format() const = 0;
  virtual const std::filesystem::path& root() const = 0;
  // Episode table, fps, embodiment, action slot and width, statistics. Actions of a robot
  // source are already in its slot's order (e.g. the 29 GR-1 dims picked from 44).
  virtual const DatasetInfo& info() const = 0;
  size_t size() const { return info().episodes.size(); }

  // Where episode i lives (a directory or file), for error messages.
  virtual std::string episode_location(size_t index) const = 0;
  // Frames of episode i by index within the episode, decoded at the stored size.
  virtual at::Tensor read_frames(size_t index,
                                 const std::vector<int64_t>& frames) const = 0;  // [N, H, W, 3] u8
  // Per-frame arrays of episode i (actions/states/hidden_motion [T, *] f32, undefined when
  // absent) and its meta; no frames.
  virtual EpisodeData read_arrays(size_t index) const = 0;

  // Episode indices whose split is `split` ("" or "all" = every episode).
  std::vector<size_t> split_indices(const std::string& split) const;
  // What `dojo data info` prints: format, counts, fps, size, cameras, dims, tasks.
  virtual nlohmann::json describe() const;
};

// The episode format as an EpisodeSource.
class EpisodeStoreSource : public EpisodeSource {
 public:
  // `camera`: one of info.json's cameras ("" or the first: video.mp4); throws dojo::Error naming
  // the dataset's cameras for another.
  explicit EpisodeStoreSource(EpisodeStore store, std::string camera = "");
  const EpisodeStore& store() const { return store_; }

  std::string format() const override { return "dojo-episodes"; }
  const std::filesystem::path& root() const override { return store_.dir(); }
  const DatasetInfo& info() const override { return store_.info(); }
  std::string episode_location(size_t index) const override { return store_.episode_dir(index).string(); }
  at::Tensor read_frames(size_t index, const std::vector<int64_t>& frames) const override;
  EpisodeData read_arrays(size_t index) const override { return store_.load_arrays(index); }
  nlohmann::json describe() const override;

 private:
  EpisodeStore store_;
  std::string camera_;
};

// A dataset's display name: the last component of its directory ("a/b/" -> "b").
std::string dataset_name(const std::filesystem::path& root);

// Options for opening any dataset format.
struct OpenOptions {
  // LeRobot: "auto" (info.json's robot_type; never the path, unlike the release), "gr1", "g1",
  // "yam", "agibot", "human" (read as action-free video) or "none" (actions not mapped to a slot).
  std::string embodiment = "auto";
  // LeRobot: video key or modality name (default: the embodiment's camera, else the first); our
  // format: one of info.json's cameras (default: the first).
  std::string camera;
  bool skip_dreamdojo_names = false;  // video folders: skip names with left/right/resize/pad
  // Two or more cameras tiled into one canvas, the first the main one (data/multi_view.h); one
  // name is the same as `camera`; empty: one camera.
  std::vector<std::string> views;
  std::string view_layout = "side_by_side";  // side_by_side | stack | grid
};

// Detects the format of `path` and opens it: info.json (our episode format), meta/info.json
// (LeRobot v2.x / v3.0), *.hdf5 beside *.mp4 (EgoDex), or a tree of video files. Throws
// dojo::Error naming the path when it is none of these.
std::shared_ptr<const EpisodeSource> open_dataset(const std::filesystem::path& path,
                                                  const OpenOptions& options = {});

// What is wrong with episode i, or "" when nothing is: its arrays read (the Parquet rows, HDF5
// datasets or safetensors behind them), are finite and have one row per frame, and every frame
// decodes (in chunks, so memory stays bounded). Messages name the file that failed.
std::string check_episode(const EpisodeSource& source, size_t index);
// A side-by-side mp4 of the first `count` episodes (at most `max_frames` frames each, 0 = all),
// frames enlarged `scale` times (nearest neighbour), labelled with their tasks.
void write_preview_video(const EpisodeSource& source, const std::filesystem::path& out, size_t count,
                         int scale, int64_t max_frames = 0);

// Statistics of actions and states over every episode of a source, in LeRobot's stats.json
// shape: {"action": {min, max, mean, std, count}, "observation.state": {...}}.
nlohmann::json compute_stats(const EpisodeSource& source);
// Stores compute_stats() output: LeRobot -> meta/stats.json (keys for other features kept),
// episode format -> the stats of info.json. Returns the file written; other formats throw.
std::filesystem::path write_stats(const EpisodeSource& source, const nlohmann::json& stats);

struct ConvertOptions {
  int height = 0, width = 0;  // centre-crop + resize frames to HxW; 0 = keep the stored size
  int64_t limit = -1;         // convert only the first N episodes (< 0: all)
  VideoFormat video_format = VideoFormat::kMp4;  // how the converted episodes store their frames
};

struct ConvertResult {
  int64_t converted = 0, kept = 0;  // kept: already present from an interrupted run
};

// Writes `source` in our episode format under `dst` (frames decoded once, actions already in
// slot order, statistics carried over or computed), so training stops paying for timestamp
// lookups, shared-file parquet decoding or 1080p decodes. Each episode directory appears
// atomically; a rerun with the same options keeps finished episodes and does the rest; a `dst`
// made from another source or with other options is refused. `on_episode` is called after each.
ConvertResult convert_dataset(const EpisodeSource& source, const std::filesystem::path& dst,
                              const ConvertOptions& options = {},
                              const std::function<void()>& on_episode = {});

}  // namespace dojo::data
