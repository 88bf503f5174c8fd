// A tree of video files read as action-free episodes (LAM training, latent-action or
// action-free pretraining): every file with extension mp4/avi/mkv/mov/webm under the root
// (recursive, sorted by path) is one episode; an optional sidecar `<name>.txt` beside it holds
// its text. DreamDojo's raw-video rule can be switched on: skip names containing left, right,
// resize or pad, and under paths containing "xdof" keep only names containing 320_240.
#pragma once

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "data/episode_source.h"

namespace dojo::data {

struct VideoFolderOptions {
  bool skip_dreamdojo_names = false;
  std::vector<std::string> extensions = {".mp4", ".avi", ".mkv", ".mov", ".webm"};
};

bool is_video_file(const std::filesystem::path& path, const VideoFolderOptions& options = {});
// True when the tree under `dir` holds at least one video file.
bool looks_like_video_folder(const std::filesystem::path& dir);
// DreamDojo's skip rule for raw human video (see above); true = skip.
bool dreamdojo_skips(const std::filesystem::path& path);

class VideoFolderDataset : public EpisodeSource {
 public:
  // Probes every video (frame count, size, fps); an unreadable one throws naming the file.
  static std::shared_ptr<VideoFolderDataset> open(const std::filesystem::path& root,
                                                  const VideoFolderOptions& options = {});

  std::string format() const override { return "video-folder"; }
  const std::filesystem::path& root() const override { return root_; }
  const DatasetInfo& info() const override { return info_; }
  std::string episode_location(size_t index) const override { return videos_.at(index).string(); }
  at::Tensor read_frames(size_t index, const std::vector<int64_t>& frames) const override;
  EpisodeData read_arrays(size_t index) const override;  // meta only: text, path

  const std::vector<std::filesystem::path>& videos() const { return videos_; }
  int64_t skipped() const { return skipped_; }

 private:
  std::filesystem::path root_;
  DatasetInfo info_;
  std::vector<std::filesystem::path> videos_;
  int64_t skipped_ = 0;
};

}  // namespace dojo::data
