// What every trainer consumes: clips of 13 frames at a random stride, centre-cropped and
// resized, with their 12 actions turned into chunk-relative, min-max normalised rows of the
// 384-d unified action vector; drawn from a weighted mixture of datasets; batched by
// background workers so that training never waits on decoding.
#pragma once

#include <ATen/core/Tensor.h>

#include <atomic>
#include <condition_variable>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "data/clip_sampler.h"
#include "data/episode_source.h"
#include "data/episode_store.h"

namespace dojo::data {

struct Clip {
  at::Tensor video;          // [T, H, W, 3] uint8, T = num_frames
  at::Tensor actions;        // [T - 1, 384] float32 unified action rows
  at::Tensor hidden_motion;  // [T, M] float32 ground-truth motion at the frames, or undefined
  // [T, K, 3] (u, v, in_view) simulator keypoints at the frames, mapped through the clip's crop and
  // resize (u, v in [0, 1] over the clip's frames), or undefined.
  at::Tensor keypoints;
  bool has_actions = false;  // false for action-free (human) video: the latent slot holds the mask
  std::string dataset;
  size_t episode = 0;
  ClipWindow window;
};

// Keypoints [..., K, 3] (u, v, in_view; u and v normalised to src_h x src_w frames) as they fall
// on frames centre-cropped to out_w:out_h and resized: points cropped away lose in_view.
at::Tensor crop_keypoints(const at::Tensor& keypoints, int64_t src_h, int64_t src_w, int64_t out_h,
                          int64_t out_w);

// Every frame of a split with its simulator keypoints, in memory, for pose probes.
struct KeypointFrames {
  at::Tensor frames;                    // [N, size, size, 3] uint8, centre-cropped and resized
  at::Tensor keypoints;                 // [N, 3, 3] (u, v, in_view) on those frames
  std::vector<std::string> embodiment;  // per frame: "robot" | "human"
};
// Throws dojo::Error naming a dataset without keypoints or a split without episodes.
KeypointFrames load_keypoint_frames(const std::vector<std::filesystem::path>& datasets,
                                    const std::string& split, int64_t size);

// One dataset seen through the clip transforms.
class ClipDataset {
 public:
  // `skip_bad`: a broken episode is skipped and counted instead of failing the run.
  ClipDataset(EpisodeStore store, ClipConfig config, const std::string& split = "train",
              bool skip_bad = false);
  // Any format (LeRobot, EgoDex, video folders, ...): see open_dataset().
  ClipDataset(std::shared_ptr<const EpisodeSource> source, ClipConfig config,
              const std::string& split = "train", bool skip_bad = false);

  const EpisodeSource& source() const { return *source_; }
  // The episode store behind the dataset; throws dojo::Error when the source is another format.
  const EpisodeStore& store() const;
  const ClipConfig& config() const { return config_; }
  const std::vector<size_t>& episodes() const { return episodes_; }

  // Reads one clip. Throws dojo::Error naming the episode on bad data. The first clip read from an
  // episode decodes all of its frames at the clip size and keeps them, with its arrays, while the
  // kept episodes fit in config.decoded_cache_mib (the first ones read stay; no eviction: clips
  // are drawn uniformly, so any set of episodes serves as well as another). A kept episode gives
  // the same clips as one decoded for each clip, bit for bit. Why: decoding a clip's frames costs
  // more CPU than a small model's training step spends outside its matrix products, and on a
  // machine whose cores the matrix products share, the decoder thread stalls them.
  Clip read(size_t episode, const ClipWindow& window) const;
  // Bytes of decoded frames kept, with those reserved by decodes under way (<= the budget; the
  // episodes' arrays, a few KiB each, are not counted).
  int64_t decoded_cache_bytes() const;
  // Samples an episode (frame-count weighted) and a window. With skip_bad, broken episodes are
  // remembered and avoided; throws when no usable episode is left.
  Clip sample(std::mt19937_64& rng) const;

  int64_t skipped_episodes() const;

 private:
  std::shared_ptr<const EpisodeSource> source_;
  ClipConfig config_;
  std::vector<size_t> episodes_;     // usable episode indices of the split
  std::vector<int64_t> cumulative_;  // cumulative window counts, for length-weighted sampling
  bool skip_bad_;
  mutable std::mutex bad_mutex_;
  mutable std::set<size_t> bad_;

  struct DecodedEpisode {
    at::Tensor frames;  // [T, H, W, 3] u8 at the clip size
    EpisodeData arrays;
  };
  // The episode decoded and kept, or nullptr when it does not fit in what is left of the budget.
  std::shared_ptr<const DecodedEpisode> decoded_episode(size_t episode) const;
  mutable std::mutex cache_mutex_;
  mutable std::map<size_t, std::shared_ptr<const DecodedEpisode>> decoded_;
  mutable int64_t decoded_bytes_ = 0;  // kept and reserved by decodes under way
};

// Datasets drawn with fixed probabilities (e.g. weights 1:2:10).
class ClipMixture {
 public:
  void add(std::shared_ptr<ClipDataset> dataset, double weight);
  size_t size() const { return datasets_.size(); }
  Clip sample(std::mt19937_64& rng) const;
  const std::vector<double>& probabilities() const { return probabilities_; }

 private:
  std::vector<std::shared_ptr<ClipDataset>> datasets_;
  std::vector<double> weights_;
  std::vector<double> probabilities_;
};

struct Batch {
  at::Tensor video;        // [B, T, H, W, 3] uint8
  at::Tensor actions;      // [B, T - 1, 384] float32
  at::Tensor has_actions;  // [B] bool
  std::vector<std::string> datasets;
  int64_t index = 0;  // position in the stream
};

// Stacks clips into a batch.
Batch collate(const std::vector<Clip>& clips);

struct LoaderOptions {
  int batch_size = 4;
  int workers = 2;           // 0: one per core
  int prefetch_batches = 4;  // batches buffered ahead of the consumer
  uint64_t seed = 0;
  // A share of a stream several consumers split (data-parallel ranks, train/data_parallel.h): the
  // n-th batch handed out is batch (n / run) * every + first + n % run of the whole stream, i.e.
  // runs of `run` consecutive batches out of every `every`. The defaults hand out every batch.
  int64_t stream_every = 1, stream_first = 0, stream_run = 1;
  int64_t stream_index(int64_t n) const {
    return n / stream_run * stream_every + stream_first + n % stream_run;
  }
};

// Background batch producer. Batch k is built from an RNG seeded by (seed, k) alone, so the
// stream is the same whatever the number of workers or their timing.
class PrefetchLoader {
 public:
  PrefetchLoader(std::shared_ptr<const ClipMixture> mixture, LoaderOptions options, int64_t first_batch = 0);
  ~PrefetchLoader();
  PrefetchLoader(const PrefetchLoader&) = delete;
  PrefetchLoader& operator=(const PrefetchLoader&) = delete;

  // Blocks until the next batch in order is ready. Rethrows a worker's error.
  Batch next();
  // Seconds the consumer spent blocked in next() (0 when workers keep up).
  double wait_seconds() const { return wait_seconds_; }

 private:
  void worker_loop();

  std::shared_ptr<const ClipMixture> mixture_;
  LoaderOptions options_;
  std::vector<std::thread> workers_;
  std::mutex mutex_;
  std::condition_variable ready_cv_, space_cv_;
  std::map<int64_t, Batch> ready_;
  int64_t next_to_make_;
  int64_t next_to_return_;
  bool stop_ = false;
  std::exception_ptr error_;
  double wait_seconds_ = 0;
};

// Seeds a generator from (seed, stream index) with splitmix64 so neighbouring indices give
// unrelated streams.
std::mt19937_64 stream_rng(uint64_t seed, uint64_t index);

}  // namespace dojo::data
