// The world model's training data: 13-frame clips encoded once by the frozen tokenizer (and, for
// human video, labelled once by the frozen LAM) into an in-memory latent cache that is also kept
// on disk, fingerprinted by the data and models that made it.
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "data/actions.h"
#include "data/episode_source.h"

namespace dojo::train {

// What goes into the 384-d action rows of a clip.
enum class ActionMode {
  kDataset,      // the dataset's own rows (robot joints in their slot; human: the latent mask)
  kLatent,       // latent slot [352, 384) := mask * LAM latent action of each frame pair
  kNone,         // all zero (action-free pretraining)
  kGroundTruth,  // human hidden motion, chunk-relative, in the latent slot (upper-bound ablation)
};
ActionMode parse_action_mode(const std::string& text);  // dataset | latent | none | ground-truth
std::string to_string(ActionMode mode);

// Which clips to cache and how.
struct LatentCacheSpec {
  std::filesystem::path dataset;
  std::string split = "train";
  std::string embodiment = "auto";  // LeRobot: the robot (data::OpenOptions::embodiment)
  std::vector<std::string> views;   // 2+ cameras tiled into one canvas (data/multi_view.h)
  std::string view_layout = "side_by_side";
  std::filesystem::path tokenizer;  // checkpoint directory
  std::filesystem::path lam;        // checkpoint directory (ActionMode::kLatent only)
  ActionMode mode = ActionMode::kDataset;
  std::vector<int> strides = {1, 2};
  int64_t hop = 2;               // window starts advance by this many frames
  int size = 0;                  // frame size fed to the tokenizer (0: the dataset's)
  int64_t max_clips = 0;         // 0: all windows
  int frames = 13;               // frames per clip, 1 + 4k (distillation rolls out 49)
  bool relative_actions = true;  // false: absolute normalised actions (ablation)
  // Robot actions normalised with these instead of the dataset's statistics (the world model's
  // own, shared by all its robot datasets); unset: the dataset's.
  std::optional<data::ArrayStats> action_stats;
  nlohmann::json to_json() const;
  // How the dataset is opened (the robot named).
  data::OpenOptions open_options() const;
};

struct LatentClips {
  torch::Tensor latents;  // [N, 16, T_lat, h, w] normalised tokenizer latents
  torch::Tensor actions;  // [N, T - 1, 384] rows after the action mode
  nlohmann::json meta;    // the spec that made it
  int64_t size() const { return latents.defined() ? latents.size(0) : 0; }
};

// Loads `cache_file` when it was made from the same spec; otherwise encodes every window of the
// split and writes the file atomically.
LatentClips load_or_build_latent_clips(const LatentCacheSpec& spec, const std::filesystem::path& cache_file);

// Concatenates clip sets (their latent shapes must agree).
LatentClips concat_latent_clips(const std::vector<LatentClips>& sets);

}  // namespace dojo::train
