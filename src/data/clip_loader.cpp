#include "data/clip_loader.h"

#include <torch/torch.h>

#include <chrono>
#include <numeric>

#include "core/error.h"
#include "core/log.h"
#include "core/runtime.h"
#include "data/embodiments.h"
#include "io/video.h"

namespace dojo::data {

std::mt19937_64 stream_rng(uint64_t seed, uint64_t index) {
  uint64_t z = seed + 0x9E3779B97F4A7C15ull * (index + 1);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  z ^= z >> 31;
  return std::mt19937_64(z);
}

ClipDataset::ClipDataset(EpisodeStore store, ClipConfig config, const std::string& split, bool skip_bad)
    : ClipDataset(std::make_shared<EpisodeStoreSource>(std::move(store)), std::move(config), split,
                  skip_bad) {}

ClipDataset::ClipDataset(std::shared_ptr<const EpisodeSource> source, ClipConfig config,
                         const std::string& split, bool skip_bad)
    : source_(std::move(source)), config_(std::move(config)), skip_bad_(skip_bad) {
  DOJO_CHECK(source_ != nullptr, "clip dataset needs a source");
  const auto& info = source_->info();
  const std::string root = source_->root().string();
  if (info.embodiment == Embodiment::kRobot) {
    DOJO_CHECK(info.action_stats.has_value() || config_.action_stats.has_value(),
               root + ": robot dataset has no action statistics");
    if (config_.action_stats)
      DOJO_CHECK(config_.action_stats->dim() == info.action_dim,
                 root + ": the given action statistics have " + std::to_string(config_.action_stats->dim()) +
                     " dimensions, the dataset's actions " + std::to_string(info.action_dim));
    DOJO_CHECK(!info.action_slot.empty(),
               root +
                   ": a robot dataset whose actions fill no slot of the 384-d layout; name the robot with "
                   "--embodiment (" +
                   embodiment_names() +
                   "; human / none for its video alone; a new robot: --embodiments FILE, docs/new_robot.md)");
  }
  int64_t total = 0;
  for (size_t index : source_->split_indices(split)) {
    int64_t windows = 0;
    for (int stride : config_.strides)
      if (window_fits(info.episodes[index].frames, stride, config_.num_frames))
        windows += info.episodes[index].frames - static_cast<int64_t>(config_.num_frames) * stride;
    if (windows == 0) continue;  // too short for any clip
    episodes_.push_back(index);
    total += windows;
    cumulative_.push_back(total);
  }
  DOJO_CHECK(!episodes_.empty(), root + ": split '" + split + "' has no episode long enough for a " +
                                     std::to_string(config_.num_frames) + "-frame clip");
}

const EpisodeStore& ClipDataset::store() const {
  const auto* s = dynamic_cast<const EpisodeStoreSource*>(source_.get());
  if (s == nullptr)
    throw Error(source_->root().string() + ": a " + source_->format() + " dataset is not an episode store");
  return s->store();
}

at::Tensor crop_keypoints(const at::Tensor& keypoints, int64_t src_h, int64_t src_w, int64_t out_h,
                          int64_t out_w) {
  // The frames were centre-cropped to the output's aspect, then scaled: normalised coordinates
  // move with the crop box and scale with it.
  const auto box = io::center_crop_box(src_h, src_w, out_w, out_h);
  auto out = keypoints.clone();  // [..., K, 3]
  auto u = out.select(-1, 0), v = out.select(-1, 1), in_view = out.select(-1, 2);
  u.mul_(static_cast<double>(src_w)).sub_(static_cast<double>(box.left)).div_(static_cast<double>(box.width));
  v.mul_(static_cast<double>(src_h)).sub_(static_cast<double>(box.top)).div_(static_cast<double>(box.height));
  in_view.mul_((u >= 0).logical_and(u <= 1).logical_and(v >= 0).logical_and(v <= 1).to(in_view.dtype()));
  return out;
}

KeypointFrames load_keypoint_frames(const std::vector<std::filesystem::path>& datasets,
                                    const std::string& split, int64_t size) {
  KeypointFrames out;
  std::vector<at::Tensor> frames, keypoints;
  for (const auto& dir : datasets) {
    const auto store = EpisodeStore::open(dir);
    const auto& info = store.info();
    DOJO_CHECK(
        info.keypoint_names.size() == 3,
        dir.string() + ": no simulator keypoints (info.json keypoint_names); make it with dojo sim generate");
    for (size_t e : store.split_indices(split)) {
      const auto ep = store.load(e);
      DOJO_CHECK(ep.keypoints.defined(), store.episode_dir(e).string() + ": no keypoints");
      const int64_t T = ep.frames.size(0);
      keypoints.push_back(
          crop_keypoints(ep.keypoints.view({T, 3, 3}), ep.frames.size(1), ep.frames.size(2), size, size));
      frames.push_back(io::resize_center_crop(ep.frames, size, size));
      out.embodiment.insert(out.embodiment.end(), static_cast<size_t>(T), to_string(info.embodiment));
    }
  }
  DOJO_CHECK(!frames.empty(), "keypoint frames: no episodes in split '" + split + "' of the given datasets");
  out.frames = torch::cat(frames);
  out.keypoints = torch::cat(keypoints);
  return out;
}

Clip ClipDataset::read(size_t episode, const ClipWindow& window) const {
  const auto& info = source_->info();
  DOJO_CHECK(episode < info.episodes.size(),
             source_->root().string() + ": episode index " + std::to_string(episode) + " out of range");
  const std::string where = source_->episode_location(episode);
  Clip clip;
  clip.dataset = info.name;
  clip.episode = episode;
  clip.window = window;
  const int64_t frames = info.episodes[episode].frames;
  DOJO_CHECK(window.steps.back() < frames, where + ": clip window ends at " +
                                               std::to_string(window.steps.back()) + " beyond " +
                                               std::to_string(frames) + " frames");

  const auto steps = torch::tensor(window.steps, torch::kLong);  // [T + 1]
  const auto decoded = decoded_episode(episode);
  EpisodeData arrays;
  if (decoded) {
    arrays = decoded->arrays;                                         // shared: only read below
    clip.video = decoded->frames.index_select(0, steps.slice(0, 1));  // [T, H, W, 3] u8
  } else {
    arrays = source_->read_arrays(episode);
    const auto raw = source_->read_frames(episode, window.frame_indices());   // [T, h, w, 3] u8
    clip.video = io::resize_center_crop(raw, config_.height, config_.width);  // [T, H, W, 3] u8
  }
  const int64_t rows = config_.num_frames - 1;
  if (rows == 0) {  // a single frame (image training): no action lies between frames
    clip.actions = human_action_placeholder(0);  // [0, 384]
    clip.has_actions = info.embodiment == Embodiment::kRobot;
  } else if (info.embodiment == Embodiment::kRobot) {
    DOJO_CHECK(arrays.actions.defined() && arrays.actions.size(0) == frames,
               where + ": robot episode has no action row per frame");
    const auto absolute = arrays.actions.index_select(0, steps);  // [T + 1, A]
    const auto& stats = config_.action_stats ? *config_.action_stats : *info.action_stats;
    const auto normalized = normalize_min_max(absolute, stats);  // [T + 1, A]
    const auto relative = config_.relative_actions ? chunk_relative(normalized, config_.action_chunk)
                                                   : normalized.slice(0, 1, rows + 1);  // [T - 1, A]
    DOJO_CHECK(relative.size(0) == rows, where + ": clip length " + std::to_string(config_.num_frames) +
                                             " - 1 is not a multiple of the action chunk");
    clip.actions = place_in_slot(relative, slot_by_name(info.action_slot));  // [T - 1, 384]
    clip.has_actions = true;
  } else {
    clip.actions = human_action_placeholder(rows);  // [T - 1, 384]
  }
  if (arrays.hidden_motion.defined())
    clip.hidden_motion = arrays.hidden_motion.index_select(0, steps.slice(0, 1));  // [T, M]
  if (arrays.keypoints.defined()) {
    const auto kp = arrays.keypoints.index_select(0, steps.slice(0, 1));  // [T, 3K]
    clip.keypoints = crop_keypoints(kp.view({kp.size(0), -1, 3}), info.height, info.width, config_.height,
                                    config_.width);  // [T, K, 3]
  }
  return clip;
}

std::shared_ptr<const ClipDataset::DecodedEpisode> ClipDataset::decoded_episode(size_t episode) const {
  const int64_t budget = config_.decoded_cache_mib * (int64_t{1} << 20);
  if (budget <= 0) return nullptr;
  const int64_t frames = source_->info().episodes[episode].frames;
  const int64_t bytes = frames * config_.height * config_.width * 3;
  {
    std::lock_guard<std::mutex> lock(cache_mutex_);
    if (auto it = decoded_.find(episode); it != decoded_.end()) return it->second;
    if (decoded_bytes_ + bytes > budget) return nullptr;
    decoded_bytes_ += bytes;  // reserved while decoding, so that workers together stay in budget
  }
  auto made = std::make_shared<DecodedEpisode>();
  try {
    made->arrays = source_->read_arrays(episode);
    // In runs of frames, so that a long episode at its source size is never in memory whole, and
    // into the kept tensor directly, so that the episode is never in memory twice.
    constexpr int64_t kRun = 32;
    made->frames = torch::empty({frames, config_.height, config_.width, 3}, torch::kUInt8);
    for (int64_t first = 0; first < frames; first += kRun) {
      const int64_t n = std::min(kRun, frames - first);
      std::vector<int64_t> indices(static_cast<size_t>(n));
      std::iota(indices.begin(), indices.end(), first);
      made->frames.narrow(0, first, n)
          .copy_(io::resize_center_crop(source_->read_frames(episode, indices), config_.height,
                                        config_.width));  // [n, H, W, 3] u8
    }
  } catch (const std::exception&) {
    // Kept from now on as "read per clip": a clip that avoids the damage (a video shorter than
    // its table says) still reads, and one that does not fails naming it, as without the cache.
    made = nullptr;
  }
  std::lock_guard<std::mutex> lock(cache_mutex_);
  const auto [it, inserted] = decoded_.emplace(episode, made);
  if (!inserted || made == nullptr) decoded_bytes_ -= bytes;  // another worker kept it first
  return it->second;
}

int64_t ClipDataset::decoded_cache_bytes() const {
  std::lock_guard<std::mutex> lock(cache_mutex_);
  return decoded_bytes_;
}

Clip ClipDataset::sample(std::mt19937_64& rng) const {
  for (int attempt = 0; attempt < 64; ++attempt) {
    const uint64_t pick = uniform_index(rng, static_cast<uint64_t>(cumulative_.back()));
    const size_t slot = std::upper_bound(cumulative_.begin(), cumulative_.end(), static_cast<int64_t>(pick)) -
                        cumulative_.begin();
    const size_t episode = episodes_[slot];
    const auto window = sample_window(source_->info().episodes[episode].frames, config_, rng);
    {
      std::lock_guard<std::mutex> lock(bad_mutex_);
      if (bad_.count(episode)) continue;
    }
    try {
      return read(episode, *window);
    } catch (const Error& e) {
      if (!skip_bad_) throw;
      std::lock_guard<std::mutex> lock(bad_mutex_);
      if (bad_.insert(episode).second) LOG_WARN("skipping bad episode: ", e.what());
      if (bad_.size() == episodes_.size()) throw Error(source_->root().string() + ": every episode is bad");
    }
  }
  throw Error(source_->root().string() + ": could not draw a usable clip after 64 attempts");
}

int64_t ClipDataset::skipped_episodes() const {
  std::lock_guard<std::mutex> lock(bad_mutex_);
  return static_cast<int64_t>(bad_.size());
}

void ClipMixture::add(std::shared_ptr<ClipDataset> dataset, double weight) {
  DOJO_CHECK(weight > 0, "mixture weight must be positive, got " + std::to_string(weight));
  if (!datasets_.empty()) {
    const auto& a = datasets_.front()->config();
    const auto& b = dataset->config();
    DOJO_CHECK(
        a.num_frames == b.num_frames && a.height == b.height && a.width == b.width,
        dataset->source().root().string() + ": clip geometry differs from the other datasets of the mixture");
  }
  datasets_.push_back(std::move(dataset));
  weights_.push_back(weight);
  double sum = 0;
  for (double w : weights_) sum += w;
  probabilities_.clear();
  for (double w : weights_) probabilities_.push_back(w / sum);
}

Clip ClipMixture::sample(std::mt19937_64& rng) const {
  DOJO_CHECK(!datasets_.empty(), "clip mixture is empty");
  // 53 random bits -> uniform double in [0, 1), the same on every platform.
  const double u = static_cast<double>(rng() >> 11) * (1.0 / 9007199254740992.0);
  double acc = 0;
  for (size_t i = 0; i < datasets_.size(); ++i) {
    acc += probabilities_[i];
    if (u < acc || i + 1 == datasets_.size()) return datasets_[i]->sample(rng);
  }
  return datasets_.back()->sample(rng);
}

Batch collate(const std::vector<Clip>& clips) {
  DOJO_CHECK(!clips.empty(), "cannot collate an empty batch");
  std::vector<at::Tensor> videos, actions;
  std::vector<uint8_t> has;
  Batch batch;
  for (const auto& c : clips) {
    videos.push_back(c.video);
    actions.push_back(c.actions);
    has.push_back(c.has_actions ? 1 : 0);
    batch.datasets.push_back(c.dataset);
  }
  batch.video = torch::stack(videos);     // [B, T, H, W, 3]
  batch.actions = torch::stack(actions);  // [B, T - 1, 384]
  batch.has_actions = torch::tensor(std::vector<int64_t>(has.begin(), has.end())).to(torch::kBool);  // [B]
  return batch;
}

PrefetchLoader::PrefetchLoader(std::shared_ptr<const ClipMixture> mixture, LoaderOptions options,
                               int64_t first_batch)
    : mixture_(std::move(mixture)),
      options_(options),
      next_to_make_(first_batch),
      next_to_return_(first_batch) {
  DOJO_CHECK(options_.batch_size > 0, "batch size must be positive");
  DOJO_CHECK(options_.workers >= 0, "loader workers must be >= 0 (0 = one per core)");
  const int workers = options_.workers > 0
                          ? options_.workers
                          : std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
  for (int i = 0; i < workers; ++i) workers_.emplace_back([this] { worker_loop(); });
}

PrefetchLoader::~PrefetchLoader() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  space_cv_.notify_all();
  ready_cv_.notify_all();
  for (auto& t : workers_) t.join();
}

void PrefetchLoader::worker_loop() {
  // Decoding threads must not each spin up a full intra-op pool.
  use_one_thread_in_this_thread();
  while (true) {
    int64_t index;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      space_cv_.wait(lock,
                     [&] { return stop_ || next_to_make_ < next_to_return_ + options_.prefetch_batches; });
      if (stop_) return;
      index = next_to_make_++;
    }
    try {
      auto rng = stream_rng(options_.seed, static_cast<uint64_t>(options_.stream_index(index)));
      std::vector<Clip> clips;
      for (int b = 0; b < options_.batch_size; ++b) clips.push_back(mixture_->sample(rng));
      Batch batch = collate(clips);
      batch.index = index;
      std::lock_guard<std::mutex> lock(mutex_);
      ready_.emplace(index, std::move(batch));
    } catch (...) {
      std::lock_guard<std::mutex> lock(mutex_);
      if (!error_) error_ = std::current_exception();
      stop_ = true;
    }
    ready_cv_.notify_all();
  }
}

Batch PrefetchLoader::next() {
  const auto start = std::chrono::steady_clock::now();
  std::unique_lock<std::mutex> lock(mutex_);
  ready_cv_.wait(lock, [&] { return error_ || ready_.count(next_to_return_) > 0; });
  if (error_ && !ready_.count(next_to_return_)) std::rethrow_exception(error_);
  Batch batch = std::move(ready_.at(next_to_return_));
  ready_.erase(next_to_return_);
  ++next_to_return_;
  lock.unlock();
  space_cv_.notify_all();
  wait_seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return batch;
}

}  // namespace dojo::data
