// LeRobot datasets (v2.0/v2.1 and v3.0) with GR00T's meta/modality.json, read as an
// EpisodeSource.
//
//   v2.x  meta/info.json, meta/episodes.jsonl, meta/tasks.jsonl, meta/stats.json or
//         meta/episodes_stats.jsonl; data/chunk-XXX/episode_XXXXXX.parquet (one per episode);
//         videos/chunk-XXX/<video_key>/episode_XXXXXX.mp4 (each starts at t = 0)
//   v3.0  meta/info.json, meta/episodes/chunk-XXX/file-XXX.parquet (one row per episode),
//         meta/tasks.parquet, meta/stats.json; data/chunk-XXX/file-XXX.parquet (rows of many
//         episodes); videos/<video_key>/chunk-XXX/file-XXX.mp4 (episodes back to back; an
//         episode starts at its from_timestamp)
// The paths come from info.json's data_path / video_path templates.
//
// Frames are located by timestamp: the row's `timestamp` (+ from_timestamp in v3.0) times the
// video's frame rate, accepted when a frame lies within 1e-4 s (LeRobot's tolerance); a
// timestamp outside the video is an error naming the file and the episode. When every
// timestamp of an episode is 0 the row index / fps is used (as DreamDojo does).
//
// Actions of a known robot are sliced by meta/modality.json (or the robot's built-in layout
// when the dataset has none) and concatenated in the order of its slot of the unified 384-d
// action vector, e.g. GR-1: left_arm 7, right_arm 7, left_hand 6, right_hand 6, waist 3 = 29
// dims in slot [0, 29). Statistics (meta/stats.json) are sliced the same way.
#pragma once

#include <deque>
#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

#include "data/episode_source.h"

namespace dojo::data {

// One named range of the concatenated state or action array (modality.json).
struct ModalityRange {
  std::string key;           // e.g. "left_arm"
  int start = 0, end = 0;    // half-open
  std::string original_key;  // parquet column it slices; "" = observation.state / action
  int width() const { return end - start; }
};

// GR00T's meta/modality.json.
struct Modality {
  std::vector<ModalityRange> state, action;
  std::map<std::string, std::string> video;  // video.<name> -> parquet/video feature key
  std::vector<std::string> annotation;
  const ModalityRange* find_action(const std::string& key) const;
  // Throws dojo::Error "WHERE: action.left_arm: ..." for missing or inconsistent fields.
  static Modality from_json(const nlohmann::json& j, const std::string& where);
};

// How one released robot maps into the unified action vector.
struct RobotLayout {
  std::string name;  // "gr1", "g1", "yam", "agibot"
  ActionSlot slot;
  std::string camera;                                     // modality video key DreamDojo reads
  std::vector<std::pair<std::string, int>> action_order;  // keys and widths, slot order
  Modality default_modality;                              // when the dataset ships none
};
// The built-in robots, then those of the user's embodiment table (data/embodiments.h).
const std::deque<RobotLayout>& robot_layouts();
// nullptr when unknown.
const RobotLayout* find_robot_layout(const std::string& name);
// The robot info.json's robot_type names: a user robot listing it (any case), else the first of
// gr1, g1, yam, agibot found in it, lower-cased ("gr1" also matches "gr-1" and "fourier"); ""
// when none. Unlike the release, which
// searches the dataset's path as well (and so reads a GR-1 set copied to a path without "gr1" with
// meaningless actions), the path is never consulted: --embodiment names the robot otherwise.
std::string detect_robot(const std::string& robot_type);

// Expands Python format templates such as
// "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet".
std::string format_path_template(const std::string& pattern,
                                 const std::map<std::string, std::string>& strings,
                                 const std::map<std::string, int64_t>& numbers, const std::string& where);

class LeRobotDataset : public EpisodeSource {
 public:
  static std::shared_ptr<LeRobotDataset> open(const std::filesystem::path& root,
                                              const OpenOptions& options = {});

  std::string format() const override { return format_; }
  const std::filesystem::path& root() const override { return root_; }
  const DatasetInfo& info() const override { return info_; }
  std::string episode_location(size_t index) const override;
  at::Tensor read_frames(size_t index, const std::vector<int64_t>& frames) const override;
  EpisodeData read_arrays(size_t index) const override;
  nlohmann::json describe() const override;

  // The unsliced `action` and `observation.state` columns of one episode (for statistics).
  EpisodeData read_raw(size_t index) const;
  const std::vector<std::string>& cameras() const { return cameras_; }
  const std::string& camera() const { return camera_; }
  const std::vector<std::string>& tasks() const { return tasks_; }
  const Modality& modality() const { return modality_; }
  const RobotLayout* layout() const { return layout_; }
  std::filesystem::path video_file(size_t index) const;
  std::filesystem::path data_file(size_t index) const;

  struct Episode {
    int64_t index = 0;  // episode_index
    int64_t length = 0;
    std::vector<std::string> tasks;
    std::filesystem::path data_file, video_file;
    double from_timestamp = 0, to_timestamp = -1;  // v3.0: the episode's span in the shared video
  };
  struct DataFile;

 private:
  // The steps of open(), in order (lerobot_open.cpp).

  // meta/info.json: format, fps, raw action/state widths and video features; true for v3.0.
  bool read_info_json();
  // The robot (chosen or detected) and its modality (meta/modality.json or the built-in layout).
  void choose_robot(const OpenOptions& options);
  // The camera to read (explicit, else the robot's, else the first video feature) and its size.
  void choose_camera(const OpenOptions& options);
  // Tasks and episodes from the version's tables, sorted by episode index.
  void read_episode_table(bool v3);
  // info_.episodes, with the splits of info.json.
  void build_episode_entries();
  // Embodiment, action names and width, and the statistics sliced into the robot's slot order.
  void set_embodiment_and_stats(const std::map<std::string, ArrayStats>& column_stats);

  std::shared_ptr<const DataFile> load_data(const std::filesystem::path& path) const;
  std::vector<int64_t> episode_rows(size_t index, const DataFile& data) const;

  std::string format_;
  std::filesystem::path root_;
  nlohmann::json info_json_;
  DatasetInfo info_;
  Modality modality_;
  const RobotLayout* layout_ = nullptr;
  std::string robot_;  // detected or chosen robot name ("" unknown)
  std::vector<std::string> cameras_;
  std::string camera_;
  std::vector<std::string> tasks_;
  std::vector<Episode> episodes_;
  int action_width_ = 0, state_width_ = 0;  // raw column widths from info.json features
  mutable std::mutex cache_mutex_;
  mutable std::map<std::string, std::shared_ptr<const DataFile>> cache_;
};

}  // namespace dojo::data
