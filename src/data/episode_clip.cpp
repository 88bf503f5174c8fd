#include "data/episode_clip.h"

#include <torch/torch.h>
#include <algorithm>
#include <nlohmann/json.hpp>

#include "core/error.h"
#include "data/clip_loader.h"
#include "data/embodiments.h"
#include "data/lerobot.h"

namespace fs = std::filesystem;

namespace dojo::data {

ActionRanges parse_action_ranges(const nlohmann::json& ranges, const std::string& where) {
  ActionRanges out;
  if (ranges.is_null()) return out;
  DOJO_CHECK(ranges.is_object(), where + ": action ranges must be an object {slot: {min, max}}");
  for (const auto& [slot, range] : ranges.items()) {
    slot_by_name(slot);  // an unknown slot name throws, listing the valid ones
    out.emplace(slot, ArrayStats::from_json(range, where + "." + slot));
  }
  return out;
}

ActionNormalization parse_action_normalization(const std::string& text) {
  if (text == "auto") return ActionNormalization::kAuto;
  if (text == "model") return ActionNormalization::kModel;
  if (text == "dataset") return ActionNormalization::kDataset;
  throw Error("unknown action normalisation '" + text + "' (auto, model, dataset)");
}

int released_frame_stride(const std::string& robot) {
  if (const auto* user = find_user_embodiment(robot)) return user->frame_stride;
  if (robot == "gr1" || robot == "g1") return 2;
  if (robot == "yam" || robot == "agibot") return 4;
  return 1;
}

RolloutData::RolloutData(const fs::path& dataset, int chunks, const ActionRanges& model_ranges,
                         const RolloutDataOptions& options)
    : dataset_(dataset) {
  DOJO_CHECK(chunks > 0, "rollout: --chunks must be positive");
  DOJO_CHECK(options.frame_stride >= 0, "rollout: --frame-stride must be positive (0: the robot's)");
  DOJO_CHECK(options.height >= 0 && options.width >= 0 && options.height % 16 == 0 && options.width % 16 == 0,
             "rollout: --frame-size must be a multiple of 16 in both dimensions");
  source_ = open_dataset(dataset, options.open);
  const auto& info = source_->info();
  const std::string root = dataset.string();
  const bool robot = info.embodiment == Embodiment::kRobot;
  // A LeRobot robot whose layout is unknown has actions but no slot to put them in.
  DOJO_CHECK(!robot || !info.action_slot.empty(),
             root +
                 ": a robot dataset whose actions fill no slot of the 384-d layout; name the robot "
                 "with --embodiment (" +
                 embodiment_names() +
                 "; human / none for its video alone; a new robot: --embodiments FILE, docs/new_robot.md)");
  // The stride is the layout's: our episode format records DojoSim at its control rate.
  const bool lerobot = source_->format().rfind("lerobot", 0) == 0;
  stride_ = options.frame_stride > 0 ? options.frame_stride
                                     : (lerobot ? released_frame_stride(info.action_slot) : 1);
  clip_.num_frames = 1 + 12 * chunks;
  clip_.strides = {stride_};
  clip_.height = options.height > 0 ? options.height : info.height;
  clip_.width = options.width > 0 ? options.width : info.width;
  if (!robot) return;

  const auto model = model_ranges.find(info.action_slot);
  const bool has_model_range = model != model_ranges.end();
  switch (options.normalization) {
    case ActionNormalization::kModel:
      DOJO_CHECK(has_model_range, root + ": the model records no action range for slot '" + info.action_slot +
                                      "' (use --action-norm dataset)");
      break;
    case ActionNormalization::kDataset:
      DOJO_CHECK(info.action_stats.has_value(),
                 root + ": no action statistics (LeRobot: meta/stats.json; `dojo data stats` writes them)");
      break;
    case ActionNormalization::kAuto:
      DOJO_CHECK(has_model_range || info.action_stats.has_value(),
                 root + ": no action statistics and the model records no range for slot '" +
                     info.action_slot + "' (LeRobot: `dojo data stats` writes meta/stats.json)");
      break;
  }
  const bool use_model = options.normalization != ActionNormalization::kDataset && has_model_range;
  if (use_model) {
    clip_.action_stats = model->second;
    DOJO_CHECK(model->second.dim() == info.action_dim,
               root + ": the model's range for slot '" + info.action_slot + "' has " +
                   std::to_string(model->second.dim()) + " dimensions, the dataset's actions " +
                   std::to_string(info.action_dim));
  }
  normalization_ = use_model ? "model" : "dataset";
}

const std::string& RolloutData::action_slot() const { return source_->info().action_slot; }

const ArrayStats& RolloutData::action_range() const {
  DOJO_CHECK(normalization_ != "none", dataset_.string() + ": action-free video has no action range");
  return clip_.action_stats ? *clip_.action_stats : *source_->info().action_stats;
}

std::string RolloutData::describe() const {
  const auto& info = source_->info();
  std::string s = dataset_.string() + " (" + source_->format() + ", " + to_string(info.embodiment);
  if (!info.action_slot.empty())
    s += ", slot " + info.action_slot + " (" + std::to_string(info.action_dim) + " actions), " +
         normalization_ + " normalisation";
  s += ", frame stride " + std::to_string(stride_) + ", " + std::to_string(clip_.height) + "x" +
       std::to_string(clip_.width) + ")";
  return s;
}

std::vector<size_t> RolloutData::episodes(const std::string& split) const {
  std::vector<size_t> out;
  for (size_t i : source_->split_indices(split))
    if (window_fits(source_->info().episodes[i].frames, stride_, clip_.num_frames)) out.push_back(i);
  return out;
}

size_t RolloutData::find(const std::string& split, const std::string& id) const {
  const auto& episodes = source_->info().episodes;
  const std::string length =
      std::to_string(clip_.num_frames) + " frames at stride " + std::to_string(stride_);
  if (id.empty()) {
    DOJO_CHECK(!source_->split_indices(split).empty(),
               dataset_.string() + ": no episodes in split '" + split + "'");
    const auto usable = this->episodes(split);
    DOJO_CHECK(!usable.empty(),
               dataset_.string() + ": no episode of split '" + split + "' is long enough for " + length);
    return usable.front();
  }
  const auto it =
      std::find_if(episodes.begin(), episodes.end(), [&](const EpisodeEntry& e) { return e.id == id; });
  DOJO_CHECK(it != episodes.end(), dataset_.string() + ": no episode '" + id + "'");
  DOJO_CHECK(window_fits(it->frames, stride_, clip_.num_frames),
             dataset_.string() + ": episode " + id + " is shorter than " + length);
  return static_cast<size_t>(it - episodes.begin());
}

EpisodeClip RolloutData::read(size_t index) const {
  const auto& info = source_->info();
  const auto window = make_window(0, stride_, clip_.num_frames);
  const auto c = ClipDataset(source_, clip_, "all").read(index, window);
  EpisodeClip out;
  out.episode = info.episodes[index].id;
  out.video = c.video;
  out.actions = c.actions;
  out.keypoints = c.keypoints;
  out.embodiment = to_string(info.embodiment);
  out.fps = info.fps / stride_;
  if (normalization_ != "none") {
    const auto arrays = source_->read_arrays(index);
    out.raw_baseline = arrays.actions[window.steps.front()].clone();  // [w]
  }
  return out;
}

at::Tensor RolloutData::raw_to_rows(const at::Tensor& raw, const at::Tensor& baseline) const {
  DOJO_CHECK(normalization_ != "none",
             dataset_.string() + ": raw commands need a robot dataset (this one is action-free video)");
  const auto& range = action_range();
  DOJO_CHECK(raw.dim() == 2 && raw.size(1) == range.dim() && raw.size(0) % 12 == 0 && raw.size(0) > 0,
             "raw actions for slot '" + action_slot() + "' must be 12 K rows of " +
                 std::to_string(range.dim()) + " values");
  ActionChunker chunker(slot_by_name(action_slot()), range, kModelActionChunk);
  if (baseline.defined()) chunker.set_baseline(baseline);
  std::vector<at::Tensor> rows;
  for (int64_t r = 0; r < raw.size(0); r += kModelActionChunk)
    rows.push_back(chunker.push(raw.slice(0, r, r + kModelActionChunk)));
  return torch::cat(rows);  // [12 K, 384]
}

EpisodeClip read_episode_clip(const fs::path& dataset, const std::string& split, const std::string& episode,
                              int chunks, const ActionRanges& model_ranges,
                              const RolloutDataOptions& options) {
  const RolloutData data(dataset, chunks, model_ranges, options);
  return data.read(data.find(split, episode));
}

}  // namespace dojo::data
