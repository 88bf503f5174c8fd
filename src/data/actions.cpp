#include "data/actions.h"

#include <torch/torch.h>

#include <cmath>
#include <deque>
#include <nlohmann/json.hpp>

#include "core/error.h"
#include "core/safetensors.h"
#include "data/embodiments.h"

namespace dojo::data {

namespace {
std::vector<ActionSlot>& slot_table() {
  static std::vector<ActionSlot> list = {slots::kGr1,    slots::kGr1Retargeted, slots::kG1,   slots::kYam,
                                         slots::kAgibot, slots::kDojoSimRobot,  slots::kMano, slots::kLatent};
  return list;
}
}  // namespace

const std::vector<ActionSlot>& all_slots() { return slot_table(); }

void add_action_slot(const std::string& name, int begin, int end) {
  static std::deque<std::string> names;  // ActionSlot::name points into it; a deque never moves them
  names.push_back(name);
  slot_table().push_back({names.back().c_str(), begin, end});
}

ActionSlot slot_by_name(const std::string& name) {
  std::string names;
  for (const auto& slot : all_slots()) {
    if (name == slot.name) return slot;
    names += (names.empty() ? "" : ", ") + std::string(slot.name);
  }
  throw Error("unknown action slot '" + name + "' (known: " + names + ")");
}

nlohmann::json ArrayStats::to_json() const {
  return {{"min", min}, {"max", max}, {"mean", mean}, {"std", std}};
}

ArrayStats ArrayStats::from_json(const nlohmann::json& j, const std::string& where) {
  ArrayStats stats;
  try {
    stats.min = j.at("min").get<std::vector<float>>();
    stats.max = j.at("max").get<std::vector<float>>();
    stats.mean = j.value("mean", std::vector<float>(stats.min.size(), 0.f));
    stats.std = j.value("std", std::vector<float>(stats.min.size(), 1.f));
  } catch (const nlohmann::json::exception& e) {
    throw Error(where + ": bad statistics (" + e.what() + ")");
  }
  if (stats.max.size() != stats.min.size() || stats.mean.size() != stats.min.size() ||
      stats.std.size() != stats.min.size())
    throw Error(where + ": statistics have mismatched lengths");
  return stats;
}

void StatsAccumulator::add(const at::Tensor& rows) {
  DOJO_CHECK(rows.dim() == 2, "statistics need a [T, D] array");
  const auto data = rows.to(torch::kFloat64).contiguous();
  const int64_t t = data.size(0);
  const int64_t d = data.size(1);
  if (min_.empty()) {
    min_.assign(d, INFINITY);
    max_.assign(d, -INFINITY);
    mean_.assign(d, 0.0);
    m2_.assign(d, 0.0);
  }
  DOJO_CHECK(static_cast<int64_t>(min_.size()) == d,
             "array width " + std::to_string(d) + " differs from earlier " + std::to_string(min_.size()));
  const double* p = data.data_ptr<double>();
  for (int64_t i = 0; i < t; ++i) {
    ++count_;
    for (int64_t k = 0; k < d; ++k) {
      const double x = p[i * d + k];
      min_[k] = std::min(min_[k], x);
      max_[k] = std::max(max_[k], x);
      const double delta = x - mean_[k];
      mean_[k] += delta / count_;
      m2_[k] += delta * (x - mean_[k]);
    }
  }
}

ArrayStats union_range(const ArrayStats& a, const ArrayStats& b) {
  DOJO_CHECK(a.dim() == b.dim(), "action statistics of different widths (" + std::to_string(a.dim()) +
                                     " and " + std::to_string(b.dim()) + ") cannot be combined");
  ArrayStats out = a;
  for (int i = 0; i < a.dim(); ++i) {
    out.min[i] = std::min(a.min[i], b.min[i]);
    out.max[i] = std::max(a.max[i], b.max[i]);
  }
  return out;
}

ArrayStats StatsAccumulator::finish() const {
  ArrayStats stats;
  for (size_t k = 0; k < min_.size(); ++k) {
    stats.min.push_back(static_cast<float>(min_[k]));
    stats.max.push_back(static_cast<float>(max_[k]));
    stats.mean.push_back(static_cast<float>(mean_[k]));
    stats.std.push_back(static_cast<float>(count_ > 1 ? std::sqrt(m2_[k] / (count_ - 1)) : 0.0));
  }
  return stats;
}

namespace {
std::pair<torch::Tensor, torch::Tensor> min_range(const ArrayStats& stats, int64_t dim) {
  DOJO_CHECK(stats.dim() == dim, "action width " + std::to_string(dim) + " does not match statistics width " +
                                     std::to_string(stats.dim()));
  const auto lo = torch::tensor(stats.min);          // [D]
  const auto range = torch::tensor(stats.max) - lo;  // [D]
  return {lo, range};
}
}  // namespace

at::Tensor normalize_min_max(const at::Tensor& actions, const ArrayStats& stats) {
  const auto [lo, range] = min_range(stats, actions.size(-1));
  const auto x = actions.to(torch::kFloat32);
  const auto constant = range.le(0);
  // Dimensions that never move carry no information: pin them at 0 rather than divide by 0.
  const auto safe_range = torch::where(constant, torch::ones_like(range), range);
  const auto normalized = 2.0 * (x - lo) / safe_range - 1.0;  // [T, D]
  return torch::where(constant, torch::zeros_like(normalized), normalized);
}

at::Tensor denormalize_min_max(const at::Tensor& normalized, const ArrayStats& stats) {
  const auto [lo, range] = min_range(stats, normalized.size(-1));
  return (normalized.to(torch::kFloat32) + 1.0) * 0.5 * range + lo;  // [T, D]
}

at::Tensor chunk_relative(const at::Tensor& actions, int chunk) {
  DOJO_CHECK(chunk > 0, "chunk size must be positive");
  DOJO_CHECK(actions.dim() == 2 && actions.size(0) >= 1 + chunk,
             "chunk_relative needs at least 1 + " + std::to_string(chunk) + " action rows, got " +
                 std::to_string(actions.dim() == 2 ? actions.size(0) : 0));
  // Trailing rows that do not fill a chunk are dropped: with 14 sampled steps the last one is
  // the action after the clip's final frame, which no frame of the clip shows the effect of.
  const int64_t n = (actions.size(0) - 1) / chunk;
  const int64_t d = actions.size(1);
  const auto body = actions.slice(0, 1, 1 + n * chunk).reshape({n, chunk, d});  // [n, chunk, D]
  // Baseline of chunk k is row chunk*k of the input (the last row before the chunk).
  const auto baselines = actions.slice(0, 0, n * chunk, chunk).unsqueeze(1);  // [n, 1, D]
  return (body - baselines).reshape({n * chunk, d});                          // [n*chunk, D]
}

at::Tensor place_in_slot(const at::Tensor& actions, const ActionSlot& slot) {
  DOJO_CHECK(actions.dim() == 2, "place_in_slot needs [T, w] actions");
  const int64_t width = actions.size(1);
  DOJO_CHECK(width <= slot.width(), "action width " + std::to_string(width) + " exceeds slot '" + slot.name +
                                        "' width " + std::to_string(slot.width()));
  auto out = torch::zeros({actions.size(0), kUnifiedActionDim}, torch::kFloat32);  // [T, 384]
  out.slice(1, slot.begin, slot.begin + width).copy_(actions);
  return out;
}

ActionChunker::ActionChunker(ActionSlot slot, ArrayStats stats, int rows_per_push)
    : slot_(slot), stats_(std::move(stats)), rows_per_push_(rows_per_push) {
  DOJO_CHECK(stats_.dim() > 0 && stats_.dim() <= slot_.width(),
             "action chunker: the range's width " + std::to_string(stats_.dim()) + " does not fit slot '" +
                 slot_.name + "'");
  DOJO_CHECK(rows_per_push_ > 0 && rows_per_push_ % kModelActionChunk == 0,
             "action chunker: a push must be a whole number of " + std::to_string(kModelActionChunk) +
                 "-row chunks, got " + std::to_string(rows_per_push_) + " rows");
}

void ActionChunker::set_baseline(const at::Tensor& raw_row) {
  DOJO_CHECK(raw_row.dim() == 1 && raw_row.size(0) == width(),
             "action baseline must have " + std::to_string(width()) + " values");
  last_ = normalize_min_max(raw_row.unsqueeze(0), stats_).squeeze(0);  // [w]
}

at::Tensor ActionChunker::push(const at::Tensor& raw_rows) {
  DOJO_CHECK(raw_rows.dim() == 2 && raw_rows.size(0) == rows_per_push_ && raw_rows.size(1) == width(),
             "an action chunk must be " + std::to_string(rows_per_push_) + " rows of " +
                 std::to_string(width()) + " values, got shape " + shape_string(raw_rows.sizes()));
  const auto normalized = normalize_min_max(raw_rows, stats_);  // [rows, w]
  if (!last_.defined()) last_ = normalized[0];
  // Baseline of model chunk k: the row before it (chunk k-1's last row, or the stream's last).
  const int64_t chunks = rows_per_push_ / kModelActionChunk;
  const auto earlier = normalized.slice(0, kModelActionChunk - 1, rows_per_push_ - 1, kModelActionChunk);
  const auto baselines = torch::cat({last_.unsqueeze(0), earlier}).unsqueeze(1);  // [chunks, 1, w]
  const auto relative = (normalized.reshape({chunks, kModelActionChunk, width()}) - baselines)
                            .reshape({rows_per_push_, width()});  // [rows, w]
  last_ = normalized[rows_per_push_ - 1].clone();
  return place_in_slot(relative, slot_);  // [rows, 384]
}

std::optional<ActionChunker> single_slot_chunker(const nlohmann::json& ranges, const std::string& where,
                                                 int rows_per_push) {
  if (!ranges.is_object() || ranges.size() != 1) return std::nullopt;
  const auto range = ranges.begin();  // not *items().begin(): that iterator is a temporary
  return ActionChunker(slot_by_name(range.key()),
                       ArrayStats::from_json(range.value(), where + "." + range.key()), rows_per_push);
}

at::Tensor human_action_placeholder(int64_t rows) {
  auto out = torch::zeros({rows, kUnifiedActionDim}, torch::kFloat32);  // [T, 384]
  out.slice(1, slots::kLatent.begin, slots::kLatent.end).fill_(1.0);
  return out;
}

}  // namespace dojo::data
