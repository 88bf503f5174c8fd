#include "serve/model_host.h"

#include <algorithm>
#include <chrono>
#include <set>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "data/episode_source.h"
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

namespace {

class StudentGenerator : public Generator {
 public:
  StudentGenerator(infer::StreamingEngine engine, std::mutex& turn)
      : engine_(std::move(engine)), turn_(turn) {}
  torch::Tensor reset(const torch::Tensor& first, uint64_t seed) override {
    std::lock_guard<std::mutex> lock(turn_);
    return engine_.reset(first.unsqueeze(0), seed)[0];  // [1, H, W, 3]
  }
  int64_t actions_per_step() const override { return engine_.actions_per_step(); }
  torch::Tensor step(const torch::Tensor& actions) override {
    std::lock_guard<std::mutex> lock(turn_);
    const auto t0 = std::chrono::steady_clock::now();
    auto frames = engine_.step(actions.unsqueeze(0))[0];  // [4, H, W, 3]
    last_step_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return frames;
  }

 private:
  infer::StreamingEngine engine_;
  std::mutex& turn_;
};

// The teacher streams chunk by chunk: 12 actions -> 12 frames, each chunk conditioned on the
// last frame of the one before (its 35 sampler steps make it slow, but it is the quality path).
class TeacherGenerator : public Generator {
 public:
  TeacherGenerator(infer::WorldModel& model, std::mutex& turn) : model_(model), turn_(turn) {}
  torch::Tensor reset(const torch::Tensor& first, uint64_t seed) override {
    std::lock_guard<std::mutex> lock(turn_);
    seed_ = seed;
    chunk_ = 0;
    last_ = model_.reconstruct_frames(first.unsqueeze(0));  // [1, H, W, 3]
    return last_;
  }
  int64_t actions_per_step() const override { return infer::WorldModel::kChunkActions; }
  torch::Tensor step(const torch::Tensor& actions) override {
    std::lock_guard<std::mutex> lock(turn_);
    const auto t0 = std::chrono::steady_clock::now();
    const auto video = model_.predict_chunk(last_, actions.unsqueeze(0), seed_ + chunk_++,
                                            model_.trained_sampler());  // [1, 13, H, W, 3]
    const auto frames = video[0].narrow(0, 1, 12);                      // [12, H, W, 3]
    last_ = frames.narrow(0, 11, 1);
    last_step_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return frames;
  }

 private:
  infer::WorldModel& model_;
  std::mutex& turn_;
  torch::Tensor last_;  // [1, H, W, 3]
  uint64_t seed_ = 0;
  int64_t chunk_ = 0;
};

}  // namespace

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
    source_ = data::open_dataset(options_.data);
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
      if (!h->spec.fast_decoder.empty()) o.fast_decoder = models::load_fast_decoder(h->spec.fast_decoder);
      h->prototype = std::make_unique<infer::StreamingEngine>(
          infer::StreamingEngine::load(h->spec.checkpoint, h->spec.tokenizer, o));
    } else {
      h->teacher = std::make_unique<infer::WorldModel>(infer::WorldModel::load(
          h->spec.checkpoint, h->spec.tokenizer, options_.device, options_.precision));
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

int ModelHost::frame_size(const std::string& model) const {
  find(model);
  // The tokenizer and DiT accept any multiple of 16; sessions use the data's size, as trained.
  return source_ ? source_->info().height : 64;
}

std::unique_ptr<Generator> ModelHost::make_generator(const std::string& model) const {
  auto& h = const_cast<Hosted&>(find(model));
  std::lock_guard<std::mutex> lock(h.turn);
  if (h.prototype) {
    infer::StreamingEngine engine(h.prototype->net(), h.prototype->tokenizer(), h.prototype->options());
    return std::make_unique<StudentGenerator>(std::move(engine), h.turn);
  }
  return std::make_unique<TeacherGenerator>(*h.teacher, h.turn);
}

std::optional<data::ActionChunker> ModelHost::chunker(const std::string& model) const {
  const auto& h = find(model);
  if (h.action_ranges.size() != 1) return std::nullopt;
  const auto& [slot, stats] = *h.action_ranges.items().begin();
  return data::ActionChunker(data::slot_by_name(slot),
                             data::ArrayStats::from_json(stats, "model actions." + slot),
                             h.spec.streaming ? 4 : 12);
}

std::optional<data::ArrayStats> ModelHost::command_stats(const std::string& model) const {
  const auto& h = find(model);
  if (h.action_ranges.size() != 1) return std::nullopt;
  const auto& [slot, stats] = *h.action_ranges.items().begin();
  return data::ArrayStats::from_json(stats, "model actions." + slot);
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
  const int size = frame_size(model);
  DOJO_CHECK(image.dim() == 3 && image.size(2) == 3, "serve: an image must be [H, W, 3]");
  if (image.size(0) == size && image.size(1) == size) return image.contiguous();
  return io::resize_center_crop(image, size, size).contiguous();
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
    models.push_back({{"name", h->spec.name},
                      {"kind", h->spec.streaming ? "student" : "teacher"},
                      {"actions_per_step", h->spec.streaming ? 4 : 12},
                      {"frames_per_step", h->spec.streaming ? 4 : 12},
                      {"decoder", h->spec.fast_decoder.empty() ? "wan" : "fast"},
                      {"action_slots", slots}});
  }
  return {{"ready", ready_.load()},
          {"models", models},
          {"embodiments", std::vector<std::string>(embodiments.begin(), embodiments.end())},
          {"action_layout", {{"width", data::kUnifiedActionDim}, {"actions_per_latent_frame", 4}}},
          {"frame_size", source_ ? source_->info().height : 64},
          {"split", options_.split},
          {"episodes", episode_ids()}};
}

}  // namespace dojo::serve
