#include "serve/model_host.h"

#include <algorithm>
#include <set>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "data/episode_source.h"
#include "data/multi_view.h"
#include "infer/generator.h"
#include "infer/streaming.h"
#include "infer/world_model.h"
#include "io/frame_ops.h"

namespace dojo::serve {

struct ModelHost::Hosted {
  ModelSpec spec;
  nlohmann::json action_ranges = nlohmann::json::object();
  std::unique_ptr<infer::StreamingEngine> prototype;  // student: weights and settings to share
  std::unique_ptr<infer::WorldModel> teacher;         // teacher: stateless between chunks
  std::mutex turn;                                    // one step of one session at a time
};

ModelHost::ModelHost(Options options) : options_(std::move(options)) {
  for (const auto& spec : options_.models) {
    auto h = std::make_shared<Hosted>();
    h->spec = spec;
    hosted_.push_back(h);
  }
}

ModelHost::~ModelHost() = default;

void ModelHost::load() {
  if (!options_.data.empty()) {
    auto open = options_.open;
    if (open.views.empty() && !hosted_.empty()) {  // the views the (first) model was trained on
      const auto dir = resolve_checkpoint_dir(hosted_.front()->spec.checkpoint);
      if (const auto tiling = data::views_of_config(Checkpoint::open(dir).config(), dir.string())) {
        open.views = tiling->cameras;
        open.view_layout = data::to_string(tiling->layout);
      }
    }
    source_ = data::open_dataset(options_.data, open);
    split_ = source_->split_indices(options_.split);
    DOJO_CHECK(!split_.empty(), options_.data.string() + ": no episodes in split '" + options_.split + "'");
  }
  for (auto& h : hosted_) {
    const auto config = Checkpoint::open(resolve_checkpoint_dir(h->spec.checkpoint)).config();
    h->action_ranges = config.value("actions", nlohmann::json::object());
    if (h->spec.streaming) {
      infer::StreamingEngine::Options o;
      o.device = options_.device;
      o.precision = options_.precision;
      o.cuda_graphs = options_.cuda_graphs;
      if (!h->spec.fast_decoder.empty()) o.fast_decoder = models::load_fast_decoder(h->spec.fast_decoder);
      if (!h->spec.text_context.empty()) o.text_context = infer::load_text_context(h->spec.text_context);
      h->prototype = std::make_unique<infer::StreamingEngine>(
          infer::StreamingEngine::load(h->spec.checkpoint, h->spec.tokenizer, o));
    } else {
      h->teacher = std::make_unique<infer::WorldModel>(infer::WorldModel::load(
          h->spec.checkpoint, h->spec.tokenizer, options_.device, options_.precision));
      if (!h->spec.text_context.empty())
        h->teacher->set_text_context(infer::load_text_context(h->spec.text_context),
                                     h->spec.text_context.string());
    }
    LOG_INFO("serve: model '", h->spec.name, "' loaded from ", h->spec.checkpoint.string());
  }
  ready_ = true;
}

const ModelHost::Hosted& ModelHost::find(const std::string& model) const {
  DOJO_CHECK(ready_, "serve: the models are still loading");
  DOJO_CHECK(!hosted_.empty(), "this server hosts no model");
  if (model.empty()) return *hosted_.front();
  for (const auto& h : hosted_)
    if (h->spec.name == model) return *h;
  std::string names;
  for (const auto& h : hosted_) names += (names.empty() ? "" : ", ") + h->spec.name;
  throw Error("unknown model '" + model + "' (this server hosts: " + names + ")");
}

std::string ModelHost::resolve(const std::string& model) const { return find(model).spec.name; }

std::pair<int, int> ModelHost::frame_shape(const std::string& model) const {
  find(model);
  // The tokenizer and DiT accept any multiple of 16; sessions use the data's size, as trained.
  if (!source_) return {64, 64};
  return {source_->info().height, source_->info().width};
}

std::unique_ptr<Generator> ModelHost::make_generator(const std::string& model) const {
  auto& h = const_cast<Hosted&>(find(model));
  std::lock_guard<std::mutex> lock(h.turn);
  if (h.prototype) {
    infer::StreamingEngine engine(h.prototype->net(), h.prototype->tokenizer(), h.prototype->options());
    return infer::make_student_generator(std::move(engine), &h.turn);
  }
  return infer::make_teacher_generator(*h.teacher, &h.turn, h.spec.teacher_steps);
}

std::optional<std::pair<data::ActionSlot, data::ArrayStats>> ModelHost::commands(const Hosted& h) const {
  // The dataset's own robot first (not a copy of its info: this runs for every session and request).
  const data::DatasetInfo* data_info = source_ ? &source_->info() : nullptr;
  if (data_info != nullptr && !data_info->action_slot.empty()) {
    const auto& info = *data_info;
    const auto slot = data::slot_by_name(info.action_slot);
    if (h.action_ranges.contains(info.action_slot))
      return std::make_pair(slot, data::ArrayStats::from_json(h.action_ranges[info.action_slot],
                                                              "model actions." + info.action_slot));
    if (info.action_stats) return std::make_pair(slot, *info.action_stats);
  }
  if (h.action_ranges.size() != 1) return std::nullopt;
  const auto range = h.action_ranges.begin();  // not *items().begin(): that iterator is a temporary
  return std::make_pair(data::slot_by_name(range.key()),
                        data::ArrayStats::from_json(range.value(), "model actions." + range.key()));
}

std::optional<data::ActionChunker> ModelHost::chunker(const std::string& model) const {
  const auto& h = find(model);
  const auto c = commands(h);
  if (!c) return std::nullopt;
  return data::ActionChunker(c->first, c->second, h.spec.streaming ? 4 : 12);
}

std::optional<data::ArrayStats> ModelHost::command_stats(const std::string& model) const {
  const auto c = commands(find(model));
  if (!c) return std::nullopt;
  return c->second;
}

std::vector<std::string> ModelHost::episode_ids() const {
  std::vector<std::string> ids;
  if (source_)
    for (size_t i : split_) ids.push_back(source_->info().episodes[i].id);
  return ids;
}

StartFrame ModelHost::start_frame(const std::string& model, const std::string& episode) const {
  DOJO_CHECK(source_, "serve: no dataset to start from (give --data, or upload an image)");
  size_t index = split_.front();
  if (!episode.empty()) {
    const auto& eps = source_->info().episodes;
    const auto it =
        std::find_if(split_.begin(), split_.end(), [&](size_t i) { return eps[i].id == episode; });
    DOJO_CHECK(it != split_.end(), "unknown episode '" + episode + "' in split '" + options_.split + "'");
    index = *it;
  }
  StartFrame s;
  s.episode = source_->info().episodes[index].id;
  s.frame = fit_image(model, source_->read_frames(index, {0})[0]);  // [H, W, 3]
  const auto arrays = source_->read_arrays(index);
  if (arrays.actions.defined() && arrays.actions.size(0) > 0) s.baseline = arrays.actions[0].clone();  // [w]
  return s;
}

torch::Tensor ModelHost::fit_image(const std::string& model, const torch::Tensor& image) const {
  const auto [height, width] = frame_shape(model);
  DOJO_CHECK(image.dim() == 3 && image.size(2) == 3, "serve: an image must be [H, W, 3]");
  if (image.size(0) == height && image.size(1) == width) return image.contiguous();
  return io::resize_center_crop(image, height, width).contiguous();
}

nlohmann::json ModelHost::capabilities() const {
  // load() fills what follows on its own thread; until it is done there is nothing to read.
  if (!ready_)
    return {{"ready", false}, {"models", nlohmann::json::array()}, {"episodes", nlohmann::json::array()}};
  nlohmann::json models = nlohmann::json::array();
  std::set<std::string> embodiments;
  for (const auto& h : hosted_) {
    nlohmann::json slots = nlohmann::json::array();
    for (const auto& [slot, stats] : h->action_ranges.items()) {
      const auto s = data::slot_by_name(slot);
      slots.push_back({{"slot", slot}, {"begin", s.begin}, {"width", stats.at("min").size()}});
      embodiments.insert(slot);
    }
    // A model that records no range for the dataset's robot is driven in its units all the same.
    if (const auto c = commands(*h); c && !h->action_ranges.contains(c->first.name)) {
      slots.push_back({{"slot", c->first.name}, {"begin", c->first.begin}, {"width", c->second.dim()}});
      embodiments.insert(c->first.name);
    }
    const int64_t per_step =
        h->spec.streaming ? infer::StreamingEngine::kActionsPerStep : infer::WorldModel::kChunkActions;
    models.push_back({{"name", h->spec.name},
                      {"kind", h->spec.streaming ? "student" : "teacher"},
                      {"actions_per_step", per_step},
                      {"frames_per_step", per_step},  // a frame per action row in both models
                      {"decoder", h->spec.fast_decoder.empty() ? "wan" : "fast"},
                      {"action_slots", slots}});
  }
  const auto* tiled = dynamic_cast<const data::MultiViewSource*>(source_.get());
  return {{"ready", ready_.load()},
          {"models", models},
          // Several cameras in one canvas: the page shows them apart (data/multi_view.h).
          {"views", tiled != nullptr ? tiled->tiling().to_json() : nlohmann::json(nullptr)},
          {"embodiments", std::vector<std::string>(embodiments.begin(), embodiments.end())},
          {"action_layout", {{"width", data::kUnifiedActionDim}, {"actions_per_latent_frame", 4}}},
          {"frame_size", source_ ? source_->info().height : 64},  // the height (clients before frame_width)
          {"frame_height", source_ ? source_->info().height : 64},
          {"frame_width", source_ ? source_->info().width : 64},
          {"split", options_.split},
          {"episodes", episode_ids()}};
}

}  // namespace dojo::serve
