#include "sim/generate.h"

#include <torch/torch.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <mutex>
#include <thread>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "core/progress.h"
#include "core/runtime.h"
#include "core/safetensors.h"
#include "data/clip_loader.h"
#include "data/episode_store.h"
#include "sim/episode.h"
#include "sim/renderer.h"
#include "sim/scene.h"
#include "sim/skills.h"

namespace fs = std::filesystem;

namespace dojo::sim {

const std::vector<std::string>& split_names() {
  static const std::vector<std::string> names = {"train", "ood-objects", "counterfactual", "novel-background",
                                                 "long-horizon"};
  return names;
}

const std::vector<std::string>& play_behavior_names() {
  static const std::vector<std::string> names = {to_string(RobotBehavior::kRandomMotion),
                                                 to_string(RobotBehavior::kTeleopPlay)};
  return names;
}

nlohmann::json GenerateOptions::to_json() const {
  // Only what determines the bytes of the episodes: workers is deliberately absent.
  nlohmann::json j = {
      {"embodiment", embodiment}, {"split", split},    {"episodes", episodes}, {"frames", frames},
      {"width", width},           {"height", height},  {"seed", seed},         {"val_fraction", val_fraction},
      {"skills", skills},         {"quality", quality}};
  // Recorded only when used, so runs from before the option still resume.
  if (play_fraction > 0) j["play_fraction"] = play_fraction;
  if (!cameras.empty()) j["cameras"] = cameras;
  if (!play_behaviors.empty()) j["play_behaviors"] = play_behaviors;
  if (video_format != data::VideoFormat::kMp4) j["video_format"] = data::to_string(video_format);
  if (!policies.empty()) {
    auto& list = j["policies"] = nlohmann::json::array();
    for (const auto& p : policies)
      list.push_back({{"name", p.name},
                      {"behavior", to_string(p.options.behavior)},
                      {"quality", p.options.quality.to_json()}});
  }
  return j;
}

namespace {

// Everything one episode needs, derived from (options, index) only.
struct PlannedEpisode {
  EpisodeSpec spec;
  std::string split;   // the split label stored in info.json
  std::string policy;  // GenerateOptions::policies: the one drawn; empty otherwise
};

int default_frames(const GenerateOptions& o) { return o.split == "long-horizon" ? 600 : 64; }

PlannedEpisode plan_episode(const GenerateOptions& o, int index) {
  const Embodiment embodiment = parse_embodiment(o.embodiment);
  auto rng = data::stream_rng(o.seed, static_cast<uint64_t>(index));
  const uint64_t scene_seed = rng();
  const uint64_t controller_seed = rng();

  SceneSampling sampling;
  sampling.width = o.width;
  sampling.height = o.height;
  PlannedEpisode plan;
  plan.split = o.split;
  ControllerSpec controller = default_controller(embodiment);

  if (embodiment == Embodiment::kHuman) {
    DOJO_CHECK(o.split == "train",
               "split '" + o.split + "' is a robot evaluation split; human data has only 'train'");
    for (const auto& name : o.skills) controller.human.skills.push_back(parse_human_skill(name));
  } else {
    if (o.split == "ood-objects") {
      sampling.object_set = ObjectSet::kHumanOnly;
    } else if (o.split == "novel-background") {
      sampling.backgrounds = BackgroundSplit::kNovel;
    } else if (o.split == "long-horizon") {
      sampling.min_objects = 3;
      sampling.max_objects = 5;
    } else if (o.split == "counterfactual") {
      static const RobotBehavior kBehaviors[] = {RobotBehavior::kPat, RobotBehavior::kReachMiss,
                                                 RobotBehavior::kPush, RobotBehavior::kRandomMotion};
      controller.robot.behavior = kBehaviors[index % 4];
    } else if (o.split == "train" && o.play_fraction > 0 &&
               data::uniform_index(rng, 1000000) < static_cast<uint64_t>(o.play_fraction * 1000000)) {
      controller.robot.behavior =
          o.play_behaviors.empty()
              ? RobotBehavior::kRandomMotion
              : parse_robot_behavior(o.play_behaviors[static_cast<size_t>(index) % o.play_behaviors.size()]);
    } else if (o.split == "train" && !o.policies.empty()) {
      const auto& drawn = o.policies[static_cast<size_t>(index) % o.policies.size()];  // in turn (play aside)
      controller.robot = drawn.options;
      plan.policy = drawn.name;
    } else if (o.split != "train") {
      std::string names;
      for (const auto& n : split_names()) names += (names.empty() ? "" : ", ") + n;
      throw UsageError("unknown split '" + o.split + "' (known: " + names + ")");
    }
    if (controller.robot.behavior == RobotBehavior::kBinPick && plan.policy.empty()) {
      std::string preset = o.quality;
      if (preset.empty()) {
        // Training data mixes policy skill so the world model sees failures as well as success.
        static const char* kMix[] = {"expert", "expert", "good", "good", "medium"};
        preset = kMix[data::uniform_index(rng, 5)];
      }
      controller.robot.quality = PolicyQuality::preset(preset);
    }
    if (o.split == "train") {
      const int val_count = static_cast<int>(std::lround(o.episodes * o.val_fraction));
      if (index >= o.episodes - val_count) plan.split = "val";
    }
  }
  plan.spec.scene = sample_scene(embodiment, sampling, scene_seed);
  plan.spec.controller = controller;
  plan.spec.num_steps = o.frames > 0 ? o.frames : default_frames(o);
  plan.spec.seed = controller_seed;
  plan.spec.extra_cameras = o.cameras;
  return plan;
}

at::Tensor rows_to_tensor(const std::vector<std::vector<float>>& rows) {
  if (rows.empty()) return {};
  const int64_t width = static_cast<int64_t>(rows.front().size());
  auto out = torch::empty({static_cast<int64_t>(rows.size()), width}, torch::kFloat32);  // [T, D]
  float* p = out.data_ptr<float>();
  for (const auto& row : rows) {
    DOJO_CHECK(static_cast<int64_t>(row.size()) == width, "ragged rows in an episode record");
    std::memcpy(p, row.data(), width * sizeof(float));
    p += width;
  }
  return out;
}

at::Tensor frames_to_tensor(const EpisodeRecord& record, const std::vector<std::vector<uint8_t>>& frames) {
  const int64_t t = static_cast<int64_t>(frames.size());
  auto out = torch::empty({t, record.height, record.width, 3}, torch::kUInt8);  // [T, H, W, 3]
  uint8_t* dst = out.data_ptr<uint8_t>();
  const size_t frame_bytes = static_cast<size_t>(record.height) * record.width * 3;
  for (const auto& frame : frames) {
    DOJO_CHECK(frame.size() == frame_bytes, "rendered frame has the wrong size");
    std::memcpy(dst, frame.data(), frame_bytes);
    dst += frame_bytes;
  }
  return out;
}

data::EpisodeData to_episode_data(const EpisodeRecord& record) {
  data::EpisodeData episode;
  episode.frames = frames_to_tensor(record, record.frames);
  for (const auto& [camera, frames] : record.views)
    episode.views.push_back({camera, frames_to_tensor(record, frames)});
  episode.actions = rows_to_tensor(record.actions);
  episode.states = rows_to_tensor(record.states);
  episode.hidden_motion = rows_to_tensor(record.hidden_motion);
  episode.keypoints = rows_to_tensor(record.keypoints);
  episode.meta = record.meta;
  return episode;
}

std::string episode_id(int index) {
  char buf[16];
  std::snprintf(buf, sizeof buf, "%06d", index);
  return buf;
}

bool episode_complete(const fs::path& dir) {
  return fs::exists(dir / "meta.json") && fs::exists(dir / "data.safetensors") &&
         (fs::exists(dir / "video.mp4") || fs::exists(dir / "video.safetensors"));
}

// Refuses to mix two different runs in one directory; records the options of a new run.
void claim_directory(const fs::path& out, const GenerateOptions& options) {
  fs::create_directories(out / "episodes");
  const fs::path record = out / "generate.json";
  const auto wanted = options.to_json();
  if (fs::exists(record)) {
    const auto existing = read_json_file(record);
    for (const auto& [key, value] : wanted.items())
      if (!existing.contains(key) || existing[key] != value)
        throw Error(out.string() + ": holds a run with different options (" + key + " = " +
                    (existing.contains(key) ? existing[key].dump() : "absent") + ", asked " + value.dump() +
                    "); use another --out or the same options to resume");
    // Options recorded only when used (play_fraction, policies): a run without one is another run.
    for (const auto& [key, value] : existing.items())
      if (!wanted.contains(key))
        throw Error(out.string() + ": holds a run with different options (" + key + " = " + value.dump() +
                    ", asked absent); use another --out or the same options to resume");
    return;
  }
  write_file_atomic(record, wanted.dump(2) + "\n");
}

// Dataset-level description and statistics, from the finished episodes in index order.
data::DatasetInfo build_info(const fs::path& out, const GenerateOptions& options,
                             const std::vector<PlannedEpisode>& plans) {
  data::DatasetInfo info;
  info.name = out.filename().string();
  if (info.name.empty()) info.name = out.parent_path().filename().string();
  info.embodiment = data::embodiment_from_string(options.embodiment, "--embodiment");
  info.fps = 10;
  info.height = options.height;
  info.width = options.width;
  info.generator = options.to_json();
  info.generator["engine"] = "dojosim";
  info.video_format = options.video_format;
  if (!options.cameras.empty()) {
    info.cameras = {"ego"};
    info.cameras.insert(info.cameras.end(), options.cameras.begin(), options.cameras.end());
  }
  data::StatsAccumulator action_stats, state_stats;
  for (size_t i = 0; i < plans.size(); ++i) {
    const fs::path dir = out / "episodes" / episode_id(static_cast<int>(i));
    const auto meta = read_json_file(dir / "meta.json");
    data::EpisodeEntry entry;
    entry.id = episode_id(static_cast<int>(i));
    entry.frames = meta.at("frames").get<int64_t>();
    entry.split = plans[i].split;
    entry.task = meta.value("task", "");
    info.episodes.push_back(entry);
    if (info.keypoint_names.empty())
      info.keypoint_names = meta.value("keypoint_names", std::vector<std::string>{});
    if (info.embodiment == data::Embodiment::kRobot) {
      const auto arrays = SafetensorsFile::open(dir / "data.safetensors");
      action_stats.add(arrays.tensor("action"));
      state_stats.add(arrays.tensor("state"));
      if (info.action_names.empty()) {
        info.action_names = meta.value("action_names", std::vector<std::string>{});
        info.state_names = meta.value("state_names", std::vector<std::string>{});
      }
    }
  }
  if (info.embodiment == data::Embodiment::kRobot) {
    info.action_stats = action_stats.finish();
    info.state_stats = state_stats.finish();
    info.action_dim = info.action_stats->dim();
    info.state_dim = info.state_stats->dim();
    info.action_slot = data::slots::kDojoSimRobot.name;
  }
  return info;
}

}  // namespace

GenerateSummary generate_dataset(const fs::path& out, const GenerateOptions& options) {
  DOJO_CHECK(options.episodes > 0, "--episodes must be positive");
  DOJO_CHECK(options.width >= 16 && options.height >= 16 && options.width <= 1280 && options.height <= 960,
             "--size must be between 16x16 and 960x1280");
  (void)parse_embodiment(options.embodiment);
  if (!options.policies.empty()) {
    DOJO_CHECK(options.embodiment == "robot" && options.split == "train",
               "--policies: only the robot train split runs a policy set");
    DOJO_CHECK(options.quality.empty(), "--policies and --quality both choose the policy; give one");
  }
  const auto& play = play_behavior_names();
  for (const auto& name : options.play_behaviors)
    DOJO_CHECK(
        std::find(play.begin(), play.end(), name) != play.end(),
        "--play-behaviors: '" + name + "' is not play (expected one of " + nlohmann::json(play).dump() + ")");

  // Plan everything up front: a bad option fails before any work is done.
  std::vector<PlannedEpisode> plans;
  for (int i = 0; i < options.episodes; ++i) plans.push_back(plan_episode(options, i));
  claim_directory(out, options);

  // Leftovers of a killed run: temp dirs are discarded, complete episodes are kept.
  std::vector<int> todo;
  GenerateSummary summary;
  for (const auto& entry : fs::directory_iterator(out / "episodes"))
    if (entry.path().filename().string().find(".tmp-") != std::string::npos) fs::remove_all(entry.path());
  for (int i = 0; i < options.episodes; ++i) {
    if (episode_complete(out / "episodes" / episode_id(i)))
      ++summary.reused;
    else
      todo.push_back(i);
  }
  if (summary.reused > 0)
    LOG_INFO(out.string(), ": resuming, ", summary.reused, " episodes already complete");

  const int workers =
      std::max(1, std::min<int>(options.workers > 0 ? options.workers
                                                    : static_cast<int>(std::thread::hardware_concurrency()),
                                static_cast<int>(todo.size())));
  Progress progress("generate " + options.embodiment + "/" + options.split, static_cast<int64_t>(todo.size()),
                    "episodes");
  std::mutex mutex;
  std::atomic<size_t> next{0};
  std::atomic<int64_t> frames{0};
  std::exception_ptr error;
  const auto start = std::chrono::steady_clock::now();
  auto work = [&] {
    // One renderer (OSMesa context) per thread; torch ops here are tiny, keep them single-threaded.
    use_one_thread_in_this_thread();
    try {
      Renderer renderer;
      while (true) {
        const size_t k = next++;
        if (k >= todo.size()) return;
        {
          std::lock_guard<std::mutex> lock(mutex);
          if (error) return;
        }
        const int index = todo[k];
        const EpisodeRecord record = run_episode(plans[index].spec, &renderer);
        data::EpisodeData episode = to_episode_data(record);
        episode.meta["split"] = plans[index].split;
        episode.meta["episode_index"] = index;
        if (!plans[index].policy.empty()) episode.meta["policy"] = plans[index].policy;
        data::write_episode(out / "episodes" / episode_id(index), episode, 10.0, options.video_format);
        frames += static_cast<int64_t>(record.frames.size());
        std::lock_guard<std::mutex> lock(mutex);
        progress.advance(1);
      }
    } catch (...) {
      std::lock_guard<std::mutex> lock(mutex);
      if (!error) error = std::current_exception();
    }
  };
  std::vector<std::thread> threads;
  for (int w = 0; w < workers; ++w) threads.emplace_back(work);
  for (auto& t : threads) t.join();
  if (error) std::rethrow_exception(error);
  progress.finish();

  summary.generated = static_cast<int>(todo.size());
  summary.frames = frames;
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();

  const auto info = build_info(out, options, plans);
  data::write_dataset_info(out, info);
  double success_sum = 0;
  int success_count = 0;
  for (int i = 0; i < options.episodes; ++i) {
    const auto meta = read_json_file(out / "episodes" / episode_id(i) / "meta.json");
    if (meta.contains("success") && meta["success"].is_number()) {
      success_sum += meta["success"].get<double>();
      ++success_count;
    }
  }
  summary.mean_success = success_count > 0 ? success_sum / success_count : std::nan("");
  return summary;
}

}  // namespace dojo::sim
