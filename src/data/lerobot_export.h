// Writes any dataset as a LeRobot v2.1 dataset (meta/info.json, episodes.jsonl, tasks.jsonl,
// stats.json, modality.json; one Parquet table per episode and one H.264 video per episode and
// camera), the layout the
// released robot sets and the LeRobot tools use. DojoSim's episodes become a robot dataset other
// tools read, and a robot the engine has not seen yet, for docs/new_robot.md.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>

#include "data/episode_source.h"

namespace dojo::data {

struct LeRobotExportOptions {
  std::string robot_type;  // info.json's robot_type (required: the path never names a robot)
  // The main camera's video feature is observation.images.<camera>; a dataset of ours recording
  // several cameras writes the others under their own names (observation.images.side, ...).
  std::string camera = "front";
  int height = 0, width = 0;  // centre-crop + resize frames to HxW; 0 = keep the stored size
  int64_t limit = -1;         // the first N episodes (< 0: all)
  int crf = 18;               // x264 quality of the videos
};

// Episodes are numbered split by split (train, val, test, then any other) so that info.json's
// "splits" ranges hold them; actions and states go out raw, one modality.json key per named
// dimension. Each episode's table and video appear atomically; a rerun with the same options keeps
// finished episodes; meta/ is written last, so an interrupted export is never read as complete. A
// `dst` holding another export is refused. Returns the episodes written and kept.
ConvertResult export_lerobot(const EpisodeSource& source, const std::filesystem::path& dst,
                             const LeRobotExportOptions& options,
                             const std::function<void()>& on_episode = {});

}  // namespace dojo::data
