// What a rollout replays from a dataset of any format: an episode's first frame and the actions
// that follow it, in the world model's layout. Used by `wm rollout`, `eval`, `wm stream`, `serve`
// and the preference study, so a LeRobot or EgoDex folder in the robot's own units works wherever
// our episode format does:
//   - the robot is named (`--embodiment gr1|g1|yam|agibot|human|none`) or read from info.json's
//     robot_type; a dataset's path is never consulted (data/lerobot.h);
//   - frames are taken at the robot's released frame stride (GR-1 and G1: every 2nd frame, YAM
//     and AgiBot: every 4th; others and human video: every frame), or the one asked for;
//   - raw actions are min-max normalised with the model's recorded range for the robot's slot or
//     with the dataset's statistics (meta/stats.json), by choice; "auto" takes the model's when it
//     records one for the slot (converted released checkpoints record none) and says which it used.
#pragma once

#include <ATen/core/Tensor.h>

#include <filesystem>
#include <map>
#include <memory>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

#include "data/actions.h"
#include "data/clip_sampler.h"
#include "data/episode_source.h"

namespace dojo::data {

// A model's action normalisation: one range per slot it was trained on (its config's "actions").
using ActionRanges = std::map<std::string, ArrayStats>;
// {slot: {min, max, ...}} -> ActionRanges; throws dojo::Error naming `where` and the slot on a
// malformed entry or an unknown slot name.
ActionRanges parse_action_ranges(const nlohmann::json& ranges, const std::string& where);

enum class ActionNormalization { kAuto, kModel, kDataset };
ActionNormalization parse_action_normalization(const std::string& text);  // auto | model | dataset

// How a rollout reads a dataset.
struct RolloutDataOptions {
  OpenOptions open;      // --embodiment, --camera (LeRobot)
  int frame_stride = 0;  // 0: the robot's released stride (1 for every other source)
  ActionNormalization normalization = ActionNormalization::kAuto;
  int height = 0, width = 0;  // frames centre-cropped and resized to this size; 0: as stored
};

// The released temporal subsampling of a robot (its LeRobot layout's name): 2 for gr1 and g1,
// 4 for yam and agibot, 1 for anything else.
int released_frame_stride(const std::string& robot);

// The first 1 + 12 K frames of one episode with its actions, as a rollout replays them.
struct EpisodeClip {
  std::string episode;
  at::Tensor video;         // [1 + 12 K, H, W, 3] uint8
  at::Tensor actions;       // [12 K, 384] normalised, chunk-relative rows in the slot
  at::Tensor keypoints;     // [1 + 12 K, 3, 3] simulator keypoints, or undefined
  at::Tensor raw_baseline;  // [w] the raw command in force at frame 0 (robots), or undefined
  std::string embodiment;   // robot | human
  double fps = 10;          // the dataset's rate divided by the stride
};

// One dataset opened for rollouts of K chunks (1 + 12 K frames each).
class RolloutData {
 public:
  // Throws dojo::Error naming the dataset when it cannot be opened, names a robot without an
  // action slot, or lacks the statistics the normalisation needs.
  RolloutData(const std::filesystem::path& dataset, int chunks, const ActionRanges& model_ranges,
              const RolloutDataOptions& options = {});

  const EpisodeSource& source() const { return *source_; }
  const std::filesystem::path& dataset() const { return dataset_; }
  const ClipConfig& clip() const { return clip_; }
  int stride() const { return stride_; }
  // Where the action ranges came from: "model", "dataset" or "none" (action-free video).
  const std::string& normalization() const { return normalization_; }
  // The slot raw commands go to and the range that normalises them (robots only).
  const std::string& action_slot() const;
  const ArrayStats& action_range() const;
  // One line for logs and reports: format, robot, slot, stride, normalisation.
  std::string describe() const;

  // Episode indices of `split` long enough for a rollout at this stride.
  std::vector<size_t> episodes(const std::string& split) const;
  // Episode `id` of `split` ("" = the first long enough). Throws dojo::Error naming the dataset
  // when there is no such episode or it is too short.
  size_t find(const std::string& split, const std::string& id) const;
  EpisodeClip read(size_t index) const;

  // Raw commands [12 K, w] in the robot's units -> rows of the model's layout [12 K, 384]:
  // normalised with action_range(), made chunk-relative with `baseline` (the command in force at
  // frame 0, normalised) as the first chunk's baseline, placed in the slot.
  at::Tensor raw_to_rows(const at::Tensor& raw, const at::Tensor& baseline) const;

 private:
  std::filesystem::path dataset_;
  std::shared_ptr<const EpisodeSource> source_;
  ClipConfig clip_;
  int stride_ = 1;
  std::string normalization_ = "none";
};

// `episode` of `split` ("" = the first long enough), in one call.
EpisodeClip read_episode_clip(const std::filesystem::path& dataset, const std::string& split,
                              const std::string& episode, int chunks, const ActionRanges& model_ranges = {},
                              const RolloutDataOptions& options = {});

}  // namespace dojo::data
