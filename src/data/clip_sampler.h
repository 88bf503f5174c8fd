// Where a training clip comes from inside an episode: which frames (13 by default, at a random
// temporal stride from {1, 2, 3, 4}) and which action rows (one extra baseline step before
// the first frame). Pure index arithmetic, kept apart from decoding so it can be tested by hand.
#pragma once

#include <cstdint>
#include <optional>
#include <random>
#include <vector>

#include "data/actions.h"

namespace dojo::data {

// What the pixel-clip trainers (LAM, tokenizer) keep decoded, per dataset and process.
constexpr int64_t kTrainingDecodedCacheMib = 512;

struct ClipConfig {
  int num_frames = 13;  // 1 conditioning frame + 12 predicted
  std::vector<int> strides = {1, 2, 3, 4};
  int action_chunk = 4;  // actions per latent frame (the VAE's temporal factor)
  // false: rows hold the normalised absolute actions at steps 1..T-1 instead of chunk-relative
  // deltas (the paper's "relative actions" ablation).
  bool relative_actions = true;
  int height = 64;  // output size after centre crop + resize
  int width = 64;
  // Robot actions are min-max normalised with these statistics instead of the dataset's own:
  // a world model's, so that datasets whose ranges differ (an evaluation split, a second
  // training set) mean the same motion by the same numbers. Must match the action width.
  std::optional<ArrayStats> action_stats;
  // Decoded episodes a ClipDataset keeps in memory at the clip's size, so that later clips of an
  // episode are sliced instead of decoded again (0: decode every clip). See ClipDataset::read. Off
  // by default: a reader of a few clips per episode (a rollout, an evaluation) would decode whole
  // episodes for them; the trainers that draw many clips turn it on (kTrainingDecodedCacheMib).
  int64_t decoded_cache_mib = 0;
};

// A clip's position in its episode. steps[0] is the action baseline, steps[1..] are the frames:
// steps[i] = start + i * stride, i = 0..num_frames. Frames are steps[1..num_frames];
// actions are read at every step and turned into num_frames - 1 chunk-relative deltas.
struct ClipWindow {
  int64_t start = 0;
  int stride = 1;
  std::vector<int64_t> steps;  // num_frames + 1 entries
  std::vector<int64_t> frame_indices() const { return {steps.begin() + 1, steps.end()}; }
};

// Builds the window for a given start and stride (no bounds check).
ClipWindow make_window(int64_t start, int stride, int num_frames);

// True when a window of this stride fits an episode of `episode_frames` frames.
bool window_fits(int64_t episode_frames, int stride, int num_frames);

// Uniform integer in [0, n) from a 64-bit engine, identical on every platform (unlike
// std::uniform_int_distribution, whose algorithm the standard leaves open).
uint64_t uniform_index(std::mt19937_64& rng, uint64_t n);

// Picks a stride uniformly among those that fit, then a start uniformly among valid starts.
// Returns nothing when the episode is too short for every stride.
std::optional<ClipWindow> sample_window(int64_t episode_frames, const ClipConfig& config,
                                        std::mt19937_64& rng);

// Every window of one stride, start advancing by `hop` (evaluation enumerates these).
std::vector<ClipWindow> all_windows(int64_t episode_frames, int stride, int num_frames, int64_t hop);

}  // namespace dojo::data
