#include "data/episode_source.h"

#include <torch/torch.h>

#include <set>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/safetensors.h"
#include "data/egodex.h"
#include "data/lerobot.h"
#include "data/multi_view.h"
#include "data/video_folder.h"
#include "io/video.h"

namespace fs = std::filesystem;

namespace dojo::data {

std::string dataset_name(const fs::path& root) {
  fs::path p = fs::absolute(root).lexically_normal();
  if (p.filename().empty()) p = p.parent_path();
  return p.filename().string();
}

std::vector<size_t> EpisodeSource::split_indices(const std::string& split) const {
  std::vector<size_t> out;
  const auto& episodes = info().episodes;
  for (size_t i = 0; i < episodes.size(); ++i)
    if (split.empty() || split == "all" || episodes[i].split == split) out.push_back(i);
  return out;
}

nlohmann::json EpisodeSource::describe() const {
  const auto& i = info();
  nlohmann::json j;
  j["format"] = format();
  j["path"] = root().string();
  j["name"] = i.name;
  j["embodiments"] = {to_string(i.embodiment)};
  j["episodes"] = i.episodes.size();
  j["frames"] = i.total_frames();
  j["fps"] = i.fps;
  j["height"] = i.height;
  j["width"] = i.width;
  j["action_dim"] = i.action_dim;
  j["state_dim"] = i.state_dim;
  j["action_slot"] = i.action_slot;
  j["has_action_stats"] = i.action_stats.has_value();
  j["splits"] = i.split_counts();
  std::set<std::string> tasks;
  for (const auto& e : i.episodes)
    if (!e.task.empty()) tasks.insert(e.task);
  j["tasks"] = std::vector<std::string>(tasks.begin(), tasks.end());
  j["cameras"] = nlohmann::json::array();
  return j;
}

EpisodeStoreSource::EpisodeStoreSource(EpisodeStore store, std::string camera)
    : store_(std::move(store)), camera_(std::move(camera)) {
  if (!camera_.empty() && store_.size() > 0) (void)store_.video_path(0, camera_);  // a camera it records
}

nlohmann::json EpisodeStoreSource::describe() const {
  auto j = EpisodeSource::describe();
  j["cameras"] = store_.info().cameras;
  return j;
}

at::Tensor EpisodeStoreSource::read_frames(size_t index, const std::vector<int64_t>& frames) const {
  // One decoder thread: the loader's parallelism comes from its workers.
  return read_video_frames(store_.video_path(index, camera_), frames,
                           /*decoder_threads=*/1);  // [N, H, W, 3] u8
}

std::shared_ptr<const EpisodeSource> open_dataset(const fs::path& path, const OpenOptions& options) {
  std::error_code ec;
  if (!fs::exists(path, ec)) throw Error(path.string() + ": no such dataset directory");
  if (!fs::is_directory(path, ec)) throw Error(path.string() + ": a dataset is a directory");
  if (options.views.size() >= 2) {  // each camera opened as a source, tiled into one canvas
    std::vector<std::shared_ptr<const EpisodeSource>> views;
    for (const auto& camera : options.views) {
      OpenOptions one = options;
      one.views.clear();
      one.camera = camera;
      views.push_back(open_dataset(path, one));
    }
    ViewTiling tiling;
    tiling.cameras = options.views;
    tiling.layout = parse_view_layout(options.view_layout);
    return std::make_shared<MultiViewSource>(std::move(views), std::move(tiling));
  }
  const std::string camera = options.views.size() == 1 ? options.views.front() : options.camera;
  if (fs::exists(path / "info.json"))
    return std::make_shared<EpisodeStoreSource>(EpisodeStore::open(path), camera);
  if (options.views.size() == 1) {
    OpenOptions one = options;
    one.views.clear();
    one.camera = camera;
    return open_dataset(path, one);
  }
  if (fs::exists(path / "meta" / "info.json")) return LeRobotDataset::open(path, options);
#ifdef DOJO_WITH_MEDIA
  if (looks_like_egodex(path)) return EgoDexDataset::open(path);
#endif
  if (looks_like_video_folder(path)) {
    VideoFolderOptions vf;
    vf.skip_dreamdojo_names = options.skip_dreamdojo_names;
    return VideoFolderDataset::open(path, vf);
  }
  throw Error(path.string() +
              ": cannot tell the dataset format (no info.json, no meta/info.json, no *.hdf5 beside *.mp4, no "
              "video files)");
}

nlohmann::json compute_stats(const EpisodeSource& source) {
  StatsAccumulator actions, states;
  const auto* lerobot = dynamic_cast<const LeRobotDataset*>(&source);
  for (size_t i = 0; i < source.size(); ++i) {
    // LeRobot stats describe the stored columns, not the slot-ordered slice.
    const EpisodeData d = lerobot ? lerobot->read_raw(i) : source.read_arrays(i);
    if (d.actions.defined() && d.actions.size(0) > 0) actions.add(d.actions);
    if (d.states.defined() && d.states.size(0) > 0) states.add(d.states);
  }
  nlohmann::json j = nlohmann::json::object();
  auto put = [&](const char* name, const StatsAccumulator& acc) {
    if (acc.count() == 0) return;
    nlohmann::json s = acc.finish().to_json();
    s["count"] = {acc.count()};
    j[name] = s;
  };
  put("action", actions);
  put("observation.state", states);
  return j;
}

fs::path write_stats(const EpisodeSource& source, const nlohmann::json& stats) {
  if (source.format().rfind("lerobot", 0) == 0) {
    const fs::path path = source.root() / "meta" / "stats.json";
    nlohmann::json j = fs::exists(path) ? read_json_file(path) : nlohmann::json::object();
    for (const auto& [key, value] : stats.items()) j[key] = value;
    write_file_atomic(path, j.dump(2) + "\n");
    return path;
  }
  if (const auto* store = dynamic_cast<const EpisodeStoreSource*>(&source)) {
    DatasetInfo info = store->info();
    if (stats.contains("action"))
      info.action_stats = ArrayStats::from_json(stats.at("action"), "stats.action");
    if (stats.contains("observation.state"))
      info.state_stats = ArrayStats::from_json(stats.at("observation.state"), "stats.observation.state");
    write_dataset_info(source.root(), info);
    return source.root() / "info.json";
  }
  throw Error(source.root().string() + ": --write works for LeRobot and the episode format, not " +
              source.format());
}

ConvertResult convert_dataset(const EpisodeSource& source, const fs::path& dst, const ConvertOptions& options,
                              const std::function<void()>& on_episode) {
  const DatasetInfo& src = source.info();
  DOJO_CHECK(fs::absolute(dst) != fs::absolute(source.root()),
             dst.string() + ": cannot convert a dataset onto itself");
  nlohmann::json job = {{"source", fs::absolute(source.root()).string()},
                        {"format", source.format()},
                        {"height", options.height},
                        {"width", options.width},
                        {"limit", options.limit}};
  if (options.video_format != VideoFormat::kMp4) job["video_format"] = to_string(options.video_format);
  const fs::path job_path = dst / "convert.json";
  if (fs::exists(job_path)) {
    if (read_json_file(job_path) != job)
      throw Error(job_path.string() +
                  ": this directory holds a conversion with other options; use another DST");
  } else {
    if (fs::exists(dst) && !fs::is_empty(dst))
      throw Error(dst.string() + ": exists and is not a conversion output");
    fs::create_directories(dst);
    write_file_atomic(job_path, job.dump(2) + "\n");
  }
  fs::create_directories(dst / "episodes");

  DatasetInfo info = src;
  info.episodes.clear();
  info.video_format = options.video_format;
  info.generator = {{"converted_from", job["source"]}, {"source_format", source.format()}};
  ConvertResult result;
  StatsAccumulator action_acc, state_acc;
  const size_t count =
      options.limit < 0 ? source.size() : std::min(source.size(), static_cast<size_t>(options.limit));
  for (size_t i = 0; i < count; ++i) {
    char id[32];
    std::snprintf(id, sizeof id, "%06zu", i);
    const fs::path dir = dst / "episodes" / id;
    EpisodeEntry entry = src.episodes[i];
    entry.id = id;
    EpisodeData arrays;
    if (fs::exists(dir / "meta.json")) {
      ++result.kept;
      if (!src.action_stats || !src.state_stats) {
        // Statistics must cover every episode, including those a previous run wrote.
        const auto file = SafetensorsFile::open(dir / "data.safetensors");
        if (file.contains("action")) arrays.actions = file.tensor("action", true).to(torch::kFloat32);
        if (file.contains("state")) arrays.states = file.tensor("state", true).to(torch::kFloat32);
      }
    } else {
      std::vector<int64_t> all(static_cast<size_t>(entry.frames));
      for (int64_t f = 0; f < entry.frames; ++f) all[static_cast<size_t>(f)] = f;
      EpisodeData episode = source.read_arrays(i);
      episode.frames = source.read_frames(i, all);  // [T, H, W, 3] u8
      if (options.height > 0 && options.width > 0)
        episode.frames =
            io::resize_center_crop(episode.frames, options.height, options.width);  // [T, h, w, 3]
      episode.meta["task"] = entry.task;
      episode.meta["source"] = source.episode_location(i);
      write_episode(dir, episode, src.fps, options.video_format);
      arrays = episode;
      ++result.converted;
    }
    if (arrays.actions.defined()) action_acc.add(arrays.actions);
    if (arrays.states.defined()) state_acc.add(arrays.states);
    info.episodes.push_back(entry);
    if (on_episode) on_episode();
  }
  if (options.height > 0 && options.width > 0) info.height = options.height, info.width = options.width;
  if (!info.action_stats && action_acc.count() > 0) info.action_stats = action_acc.finish();
  if (!info.state_stats && state_acc.count() > 0) info.state_stats = state_acc.finish();
  if (info.state_stats && info.state_dim == 0) info.state_dim = info.state_stats->dim();
  if (info.embodiment == Embodiment::kHuman)
    info.action_dim = info.state_dim = 0, info.action_stats.reset(), info.state_stats.reset();
  write_dataset_info(dst, info);
  return result;
}

std::string check_episode(const EpisodeSource& source, size_t index) {
  const auto& entry = source.info().episodes.at(index);
  const std::string where = source.episode_location(index);
  try {
    const EpisodeData arrays = source.read_arrays(index);
    for (const auto& [name, array] :
         {std::pair<const char*, const at::Tensor&>{"actions", arrays.actions}, {"states", arrays.states}}) {
      if (!array.defined()) continue;
      if (array.size(0) != entry.frames)
        return where + ": " + name + " have " + std::to_string(array.size(0)) + " rows for " +
               std::to_string(entry.frames) + " frames";
      if (!torch::isfinite(array).all().item<bool>())
        return where + ": " + name + " hold NaN or infinite values";
    }
    constexpr int64_t kChunk = 64;
    for (int64_t start = 0; start < entry.frames; start += kChunk) {
      std::vector<int64_t> frames;
      for (int64_t f = start; f < std::min(entry.frames, start + kChunk); ++f) frames.push_back(f);
      const at::Tensor decoded = source.read_frames(index, frames);
      if (decoded.size(0) != static_cast<int64_t>(frames.size()))
        return where + ": frames " + std::to_string(start) + "+ decoded " + std::to_string(decoded.size(0)) +
               " of " + std::to_string(frames.size());
    }
    return "";
  } catch (const std::exception& e) {
    return e.what();
  }
}

void write_preview_video(const EpisodeSource& source, const fs::path& out, size_t count, int scale,
                         int64_t max_frames) {
  DOJO_CHECK(scale >= 1, "preview scale must be at least 1");
  std::vector<at::Tensor> videos;
  std::vector<std::string> labels;
  for (size_t i = 0; i < std::min(source.size(), count); ++i) {
    const auto& entry = source.info().episodes[i];
    const int64_t n = max_frames > 0 ? std::min(max_frames, entry.frames) : entry.frames;
    std::vector<int64_t> frames(static_cast<size_t>(n));
    for (int64_t f = 0; f < n; ++f) frames[static_cast<size_t>(f)] = f;
    at::Tensor video = source.read_frames(i, frames);  // [T, H, W, 3] u8
    if (scale > 1) video = video.repeat_interleave(scale, 1).repeat_interleave(scale, 2);
    videos.push_back(video);
    labels.push_back(entry.task.empty() ? entry.id : entry.task);
  }
  DOJO_CHECK(!videos.empty(), source.root().string() + ": no episodes to preview");
  io::write_comparison_video(out.string(), videos, labels, source.info().fps);
}

}  // namespace dojo::data
