// Action transforms of the clip pipeline: min-max normalisation, chunk-relative deltas and
// placement into the 384-d unified action vector whose slot map the released checkpoints use.
//
// Order of operations (as in the released data loader):
//   absolute actions a[0..13] (14 sampled steps; step 0 is only the baseline)
//     -> a_n = normalize_min_max(a)                  per-dimension to [-1, 1]
//     -> d   = chunk_relative(a_n, 4)                d[t..t+3] = a_n[t..t+3] - a_n[t-1], t = 1, 5, 9
//     -> v   = place_in_slot(d, slot)                [12, 384], zeros elsewhere
#pragma once

#include <ATen/core/Tensor.h>

#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace dojo::data {

constexpr int kUnifiedActionDim = 384;

// A [begin, end) range of the unified action vector owned by one embodiment.
struct ActionSlot {
  const char* name = "";
  int begin = 0;
  int end = 0;
  int width() const { return end - begin; }
};

// The official slots plus DojoSim's. DojoSim's robot arm lives in the reserved range
// [169, 220), which no released embodiment fills, so a converted official checkpoint and a
// DojoSim post-training run never fight over columns of the action MLP.
namespace slots {
inline constexpr ActionSlot kGr1{"gr1", 0, 29};
inline constexpr ActionSlot kGr1Retargeted{"gr1_retargeted", 29, 58};
inline constexpr ActionSlot kG1{"g1", 58, 101};
inline constexpr ActionSlot kYam{"yam", 101, 147};
inline constexpr ActionSlot kAgibot{"agibot", 147, 169};
inline constexpr ActionSlot kDojoSimRobot{"dojosim_robot", 169, 220};  // uses [169, 169 + action_dim)
inline constexpr ActionSlot kMano{"mano", 220, 352};
inline constexpr ActionSlot kLatent{"latent", 352, 384};
}  // namespace slots

// All named slots, in order; lookup by name throws dojo::Error listing the valid names.
const std::vector<ActionSlot>& all_slots();
ActionSlot slot_by_name(const std::string& name);

// Per-dimension statistics of one array (actions or states) over a dataset.
struct ArrayStats {
  std::vector<float> min, max, mean, std;
  int dim() const { return static_cast<int>(min.size()); }
  nlohmann::json to_json() const;
  static ArrayStats from_json(const nlohmann::json& j, const std::string& where);
};

// The range covering both: elementwise min of the minima and max of the maxima (mean and std
// are those of `a`; min-max normalisation reads only the range). Throws on different widths.
ArrayStats union_range(const ArrayStats& a, const ArrayStats& b);

// Accumulates ArrayStats over many [T, D] arrays (Welford for mean/std).
class StatsAccumulator {
 public:
  void add(const at::Tensor& rows);  // [T, D] float
  ArrayStats finish() const;
  int64_t count() const { return count_; }

 private:
  std::vector<double> min_, max_, mean_, m2_;
  int64_t count_ = 0;
};

// a_n = 2 (a - min) / (max - min) - 1; dimensions with max == min map to 0.
at::Tensor normalize_min_max(const at::Tensor& actions, const ArrayStats& stats);  // [T, D] -> [T, D]
at::Tensor denormalize_min_max(const at::Tensor& normalized, const ArrayStats& stats);

// Chunk-relative deltas: input [R, D] (row 0 = baseline), n = (R - 1) / chunk, output
// [n*chunk, D] with out[j] = in[1 + j] - in[chunk * (j / chunk)]: every chunk of `chunk` rows
// is expressed relative to the last row before it. Rows past the last full chunk are dropped
// (14 sampled steps -> 12 deltas).
at::Tensor chunk_relative(const at::Tensor& actions, int chunk = 4);

// Writes `actions` [T, w] into columns [slot.begin, slot.begin + w) of a zero [T, 384] tensor.
at::Tensor place_in_slot(const at::Tensor& actions, const ActionSlot& slot);

// The chunk of rows the world models were trained to read relative to one baseline (one latent
// frame's actions): chunk_relative(actions, kModelActionChunk) in the clip pipeline.
constexpr int kModelActionChunk = 4;

// A live stream of raw commands in the embodiment's own units, turned into the rows a world
// model was trained on: min-max normalised with the model's range, made relative in chunks of
// kModelActionChunk rows to the last row before each chunk (the previous chunk's last row, or the
// baseline), placed in the slot. A push takes `rows_per_push` rows (4 for the streaming student,
// 12 for the teacher's chunked sampler): a push of 12 is three model chunks, each relative to its
// own baseline, exactly as chunk_relative(·, 4) makes the training clips. What a streaming or
// teleoperation client sends goes through this.
class ActionChunker {
 public:
  ActionChunker(ActionSlot slot, ArrayStats stats, int rows_per_push = kModelActionChunk);
  // The command in force at the start frame, [w]. Without one, the first chunk's first row
  // serves as its own baseline.
  void set_baseline(const at::Tensor& raw_row);
  // raw [rows_per_push, w] -> [rows_per_push, 384]. Throws dojo::Error on a wrong shape.
  at::Tensor push(const at::Tensor& raw_rows);
  int width() const { return stats_.dim(); }
  int rows_per_push() const { return rows_per_push_; }
  void reset() { last_ = at::Tensor(); }

 private:
  ActionSlot slot_;
  ArrayStats stats_;
  int rows_per_push_;
  at::Tensor last_;  // the last raw row seen, normalised [w]
};

// The chunker of a model whose recorded action ranges ({slot name: ArrayStats json}, as its
// config's "actions") hold exactly one slot; none when they hold several or none, since raw
// commands then do not say which embodiment they drive. `where` names the ranges in errors.
std::optional<ActionChunker> single_slot_chunker(const nlohmann::json& ranges, const std::string& where,
                                                 int rows_per_push = kModelActionChunk);

// Human video carries no actions: zeros everywhere, ones in the latent slot. The ones act as
// the mask the world model multiplies with the LAM's latent actions.
at::Tensor human_action_placeholder(int64_t rows);

}  // namespace dojo::data
