#include "data/video_folder.h"

#include <torch/torch.h>

#include <algorithm>
#include <fstream>

#include "core/error.h"
#include "core/log.h"
#include "core/text.h"
#include "io/video.h"

namespace fs = std::filesystem;

namespace dojo::data {

namespace {

std::string read_text(const fs::path& path) {
  std::ifstream in(path);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  while (!text.empty() && (text.back() == '\n' || text.back() == '\r' || text.back() == ' ')) text.pop_back();
  return text;
}

}  // namespace

bool is_video_file(const fs::path& path, const VideoFolderOptions& options) {
  const std::string ext = ascii_lower(path.extension().string());
  return std::find(options.extensions.begin(), options.extensions.end(), ext) != options.extensions.end();
}

bool looks_like_video_folder(const fs::path& dir) {
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(dir, ec); !ec && it != fs::recursive_directory_iterator();
       it.increment(ec))
    if (it->is_regular_file() && is_video_file(it->path())) return true;
  return false;
}

bool dreamdojo_skips(const fs::path& path) {
  const std::string name = path.filename().string();
  if (path.string().find("xdof") != std::string::npos) return name.find("320_240") == std::string::npos;
  for (const char* word : {"left", "right", "resize", "pad"})
    if (name.find(word) != std::string::npos) return true;
  return false;
}

std::shared_ptr<VideoFolderDataset> VideoFolderDataset::open(const fs::path& root,
                                                             const VideoFolderOptions& options) {
  if (!fs::is_directory(root)) throw Error(root.string() + ": not a directory");
  auto ds = std::shared_ptr<VideoFolderDataset>(new VideoFolderDataset());
  ds->root_ = root;
  std::vector<fs::path> found;
  for (const auto& e :
       fs::recursive_directory_iterator(root, fs::directory_options::follow_directory_symlink))
    if (e.is_regular_file() && is_video_file(e.path(), options)) found.push_back(e.path());
  std::sort(found.begin(), found.end());
  DatasetInfo& info = ds->info_;
  info.name = dataset_name(root);
  info.embodiment = Embodiment::kHuman;
  for (const auto& path : found) {
    if (options.skip_dreamdojo_names && dreamdojo_skips(fs::relative(path, root))) {
      ++ds->skipped_;
      continue;
    }
    const io::VideoInfo v = io::probe_video(path.string());  // throws naming the file
    if (v.frames <= 0) throw Error(path.string() + ": video has no frames");
    if (ds->videos_.empty()) {
      info.fps = v.fps > 0 ? v.fps : 30;
      info.height = v.height;
      info.width = v.width;
    }
    EpisodeEntry entry;
    entry.id = fs::relative(path, root).string();
    entry.frames = v.frames;
    entry.split = "train";
    fs::path sidecar = path;
    sidecar.replace_extension(".txt");
    if (fs::exists(sidecar)) entry.task = read_text(sidecar);
    info.episodes.push_back(entry);
    ds->videos_.push_back(path);
  }
  if (ds->videos_.empty())
    throw Error(
        root.string() + ": no video files (mp4/avi/mkv/mov/webm)" +
        (ds->skipped_ ? " left after skipping " + std::to_string(ds->skipped_) + " by name" : std::string()));
  return ds;
}

at::Tensor VideoFolderDataset::read_frames(size_t index, const std::vector<int64_t>& frames) const {
  io::VideoReaderOptions options;
  options.threads = 1;  // the loader's parallelism comes from its workers
  io::VideoReader reader(videos_.at(index).string(), options);
  return reader.read_frames(frames);  // [N, H, W, 3] u8
}

EpisodeData VideoFolderDataset::read_arrays(size_t index) const {
  EpisodeData d;
  d.meta["task"] = info_.episodes.at(index).task;
  d.meta["path"] = videos_.at(index).string();
  return d;
}

}  // namespace dojo::data
