#include "serve/study_create.h"

#include <algorithm>
#include <cstdio>
#include <set>

#include "core/atomic_file.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "data/episode_clip.h"
#include "io/video.h"
#include "serve/model_host.h"

namespace dojo::serve {

namespace fs = std::filesystem;

namespace {

void check_names(const std::vector<std::string>& models) {
  DOJO_CHECK(models.size() >= 2, "study: compare at least two models");
  std::set<std::string> seen;
  for (const auto& m : models) {
    DOJO_CHECK(!m.empty() && m.find_first_of("|/\\ ") == std::string::npos && m != "truth",
               "study: model name '" + m + "' must be non-empty, not 'truth', without '|', '/' or spaces");
    DOJO_CHECK(seen.insert(m).second, "study: model name '" + m + "' given twice");
  }
}

std::string numbered(size_t index) {
  char number[24];  // room for any size_t: GCC checks the bound
  std::snprintf(number, sizeof number, "%03zu", index);
  return number;
}

// Writes a clip under a temporary name and renames it into place.
void write_clip(const fs::path& path, const torch::Tensor& frames, double fps) {  // [T, H, W, 3]
  const auto partial = path.parent_path() / ("." + path.stem().string() + ".partial.mp4");
  io::VideoWriterOptions w;
  w.fps = fps;
  io::write_video(partial.string(), frames, w);
  fs::rename(partial, path);
}

}  // namespace

Study create_study_from_models(const StudyFromModels& o) {
  std::vector<std::string> names;
  for (const auto& m : o.models) names.push_back(m.name);
  check_names(names);
  DOJO_CHECK(o.episodes >= 1 && o.chunks >= 1, "study: --episodes and --chunks must be at least 1");
  ModelHost::Options host_options;
  for (const auto& m : o.models) {
    ModelSpec spec;
    spec.name = m.name;
    spec.streaming = m.student;
    spec.checkpoint = m.checkpoint;
    spec.tokenizer = o.tokenizer;
    spec.fast_decoder = m.fast_decoder;
    host_options.models.push_back(spec);
  }
  host_options.data = o.data;
  host_options.split = o.split;
  host_options.device = o.device;
  host_options.precision = o.precision;
  ModelHost host(host_options);
  host.load();

  auto episodes = host.episode_ids();
  DOJO_CHECK(!episodes.empty(), o.data.string() + ": no episodes in split '" + o.split + "'");
  episodes.resize(std::min<size_t>(episodes.size(), static_cast<size_t>(o.episodes)));

  Study study;
  study.dir = o.dir;
  study.name = o.name.empty() ? o.dir.filename().string() : o.name;
  study.models = names;
  for (size_t e = 0; e < episodes.size(); ++e) {
    const auto& episode = episodes[e];
    StudyItem item;
    item.id = episode;
    const auto folder = fs::path("videos") / numbered(e);  // episode ids may hold '/'; folders are numbered
    fs::create_directories(o.dir / folder);
    // A rerun re-uses clips only when they were made from the same episode, models and settings.
    nlohmann::json source = {{"episode", episode}, {"data", o.data.string()},
                             {"split", o.split},   {"chunks", o.chunks},
                             {"seed", o.seed},     {"tokenizer", o.tokenizer.string()}};
    for (const auto& m : o.models)
      source["models"][m.name] = {m.checkpoint.string(), m.student, m.fast_decoder.string()};
    const auto manifest = o.dir / folder / "source.json";
    if (!fs::exists(manifest) || read_json_file(manifest) != source) {
      for (const auto& entry : fs::directory_iterator(o.dir / folder)) fs::remove(entry.path());
      write_file_atomic(manifest, source.dump(2) + "\n");
    }
    for (const auto& m : o.models) {
      // Each model reads the clip with its own action ranges (pretrained and post-trained models
      // may normalise the same commands differently).
      const auto config = Checkpoint::open(resolve_checkpoint_dir(m.checkpoint)).config();
      const auto clip =
          data::read_episode_clip(o.data, o.split, episode, o.chunks,
                                  data::parse_action_ranges(config.value("actions", nlohmann::json::object()),
                                                            m.checkpoint.string()));
      if (item.truth.empty()) {
        item.truth = (folder / "truth.mp4").string();
        if (!fs::exists(o.dir / item.truth)) write_clip(o.dir / item.truth, clip.video, clip.fps);
      }
      item.videos[m.name] = (folder / (m.name + ".mp4")).string();
      if (fs::exists(o.dir / item.videos[m.name])) continue;  // rendered by an earlier run
      auto generator = host.make_generator(m.name);
      const int64_t per_step = generator->actions_per_step();
      std::vector<torch::Tensor> frames = {generator->reset(clip.video[0], o.seed)};
      for (int64_t i = 0; i + per_step <= clip.actions.size(0); i += per_step)
        frames.push_back(generator->step(clip.actions.narrow(0, i, per_step)));  // [n, H, W, 3]
      write_clip(o.dir / item.videos[m.name], torch::cat(frames), clip.fps);     // [1 + 12 K, H, W, 3]
      LOG_INFO("study: ", episode, " / ", m.name, " rendered");
    }
    study.items.push_back(std::move(item));
  }
  study.save();
  return Study::open(o.dir);
}

Study create_study_from_videos(const fs::path& dir, const fs::path& source,
                               const std::vector<std::string>& models, const std::string& name) {
  check_names(models);
  DOJO_CHECK(fs::is_directory(source),
             source.string() + ": not a directory of clips (SOURCE/ID/truth.mp4 ...)");
  std::vector<fs::path> folders;
  for (const auto& entry : fs::directory_iterator(source))
    if (entry.is_directory()) folders.push_back(entry.path());
  std::sort(folders.begin(), folders.end());
  DOJO_CHECK(!folders.empty(), source.string() + ": no item folders (SOURCE/ID/truth.mp4 ...)");
  Study study;
  study.dir = dir;
  study.name = name.empty() ? dir.filename().string() : name;
  study.models = models;
  for (size_t index = 0; index < folders.size(); ++index) {
    const auto& folder = folders[index];
    StudyItem item;
    item.id = folder.filename().string();
    const auto target = fs::path("videos") / numbered(index);  // URLs stay plain whatever the names
    fs::create_directories(dir / target);
    const auto copy = [&](const std::string& clip) {
      const auto from = folder / (clip + ".mp4");
      DOJO_CHECK(fs::is_regular_file(from),
                 from.string() + ": missing (every item needs truth.mp4 and one clip per model)");
      fs::copy_file(from, dir / target / (clip + ".mp4"), fs::copy_options::overwrite_existing);
      return (target / (clip + ".mp4")).string();
    };
    item.truth = copy("truth");
    for (const auto& m : models) item.videos[m] = copy(m);
    study.items.push_back(std::move(item));
  }
  study.save();
  return Study::open(dir);
}

}  // namespace dojo::serve
