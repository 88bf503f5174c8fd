#include "train/train_util.h"

#include <ATen/CPUGeneratorImpl.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <deque>
#include <fstream>
#include <map>
#include <set>
#include <sstream>

#include "core/atomic_file.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/state_dict.h"
#include "train/data_parallel.h"
#include "train/train_loop.h"

namespace dojo::train {
// The optimizer keys its state by the parameter's TensorImpl address.
std::string optimizer_state_key(const torch::Tensor& p) {
  return c10::guts::to_string(p.unsafeGetTensorImpl());
}

NamedTensors adamw_state(const torch::optim::AdamW& optimizer, const torch::nn::Module& module,
                         const std::string& prefix) {
  NamedTensors out;
  const auto& state = optimizer.state();
  for (const auto& item : module.named_parameters()) {
    auto it = state.find(optimizer_state_key(item.value()));
    if (it == state.end()) continue;
    const auto& st = static_cast<const torch::optim::AdamWParamState&>(*it->second);
    const auto base = prefix + item.key();
    out.emplace_back(base + ".exp_avg", st.exp_avg());
    out.emplace_back(base + ".exp_avg_sq", st.exp_avg_sq());
    out.emplace_back(base + ".step", torch::tensor(static_cast<int64_t>(st.step()), torch::kLong));
  }
  return out;
}

void load_adamw_state(torch::optim::AdamW& optimizer, const torch::nn::Module& module,
                      const NamedTensors& tensors, const std::string& prefix) {
  std::map<std::string, torch::Tensor> by_name(tensors.begin(), tensors.end());
  auto& state = optimizer.state();
  for (const auto& item : module.named_parameters()) {
    const auto base = prefix + item.key();
    auto avg = by_name.find(base + ".exp_avg");
    if (avg == by_name.end()) continue;
    const auto& p = item.value();
    auto st = std::make_unique<torch::optim::AdamWParamState>();
    st->exp_avg(avg->second.clone().to(p.device()));
    st->exp_avg_sq(by_name.at(base + ".exp_avg_sq").clone().to(p.device()));
    st->step(by_name.at(base + ".step").item<int64_t>());
    state[optimizer_state_key(p)] = std::move(st);
  }
}

NamedTensors named_adamw_state(NamedTensors tensors, const torch::nn::Module& module,
                               const std::string& prefix) {
  const auto params = module.named_parameters();
  for (auto& [name, t] : tensors) {
    if (name.rfind("adam.", 0) != 0) continue;
    const auto dot = name.find('.', 5);
    if (dot == std::string::npos) continue;
    size_t index = 0;
    try {
      index = std::stoul(name.substr(5, dot - 5));
    } catch (const std::exception&) {
      continue;
    }
    DOJO_CHECK(index < params.size(), "optimizer state '" + name + "' names parameter " +
                                          std::to_string(index) + " but the model has " +
                                          std::to_string(params.size()));
    name = prefix + params[index].key() + name.substr(dot);
  }
  return tensors;
}

LossCurve::LossCurve(std::filesystem::path path, const std::string& header, int64_t resume_step)
    : path_(std::move(path)) {
  std::ifstream in(path_);
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty()) continue;
    if (rows_.empty()) {  // header of the existing file
      rows_.push_back(line);
      continue;
    }
    int64_t step = 0;
    try {
      step = std::stoll(line.substr(0, line.find(',')));
    } catch (const std::exception&) {
      continue;  // a torn or foreign row: drop it
    }
    if (step <= resume_step) rows_.push_back(line);
  }
  if (rows_.empty() || rows_.front() != header) rows_.assign({header});
}

void LossCurve::write() const {
  std::string text;
  for (const auto& r : rows_) text += r + "\n";
  write_file_atomic(path_, text);
}

torch::Generator cpu_generator(uint64_t seed) { return at::make_generator<at::CPUGeneratorImpl>(seed); }

torch::Generator step_generator(uint64_t seed, int64_t step) {
  return cpu_generator(seed * 0x9E3779B97F4A7C15ULL + static_cast<uint64_t>(step) + 1);
}

void save_with_adamw(const std::filesystem::path& dir, CheckpointData data,
                     const torch::optim::AdamW& optimizer, const torch::nn::Module& module, int64_t step) {
  TrainerState state;
  state.step = step;
  state.tensors = adamw_state(optimizer, module);
  data.trainer = state;
  save_checkpoint(dir, data);
}

int64_t resume_with_adamw(const std::filesystem::path& dir, torch::nn::Module& module,
                          const std::string& prefix, torch::optim::AdamW& optimizer) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  LoadOptions opts;
  opts.prefix = prefix;
  load_state_dict(module, ckpt.model(), opts);
  load_adamw_state(optimizer, module, ckpt.trainer_tensors().tensors(/*copy=*/true));
  return ckpt.step();
}

torch::Tensor gaussian_blur(const torch::Tensor& images, const torch::Tensor& sigma) {
  constexpr int64_t kRadius = 3;
  auto out = images.clone();
  const auto offsets = torch::arange(-kRadius, kRadius + 1, torch::kFloat32);  // [7]
  for (int64_t b = 0; b < images.size(0); ++b) {
    const double s = sigma[b].item<double>();
    if (s <= 0) continue;
    auto k = torch::exp(-offsets.pow(2) / (2 * s * s));
    k = (k / k.sum()).to(images.dtype());
    const auto x = images[b].unsqueeze(1);  // [C, 1, S, S]: channels as a batch
    const std::vector<int64_t> one = {1, 1}, pad_w = {0, kRadius}, pad_h = {kRadius, 0};
    const auto h = torch::conv2d(x, k.view({1, 1, 1, -1}), torch::Tensor(), one, pad_w);
    out[b] = torch::conv2d(h, k.view({1, 1, -1, 1}), torch::Tensor(), one, pad_h).squeeze(1);
  }
  return out;
}

torch::Tensor soften_like_generated(const torch::Tensor& images, double blur_probability, double brightness,
                                    torch::Generator& gen) {
  const int64_t B = images.size(0);
  const auto offset = (torch::rand({B, 1, 1, 1}, gen) * 2 - 1) * brightness;
  const auto blurred = torch::rand({B}, gen) < blur_probability;
  const auto sigma = (torch::rand({B}, gen) * 1.2 + 0.3) * blurred.to(torch::kFloat32);
  return gaussian_blur(images, sigma).add(offset).clamp(0, 1);
}

AdamwRun run_adamw_loop(torch::nn::Module& model, const AdamwLoop& loop,
                        const std::function<CheckpointData()>& checkpoint,
                        const std::function<AdamwStep(const LoopStep&, int64_t, torch::Generator&)>& step,
                        const std::function<void(int64_t)>& after_step) {
  auto& group = data_parallel();
  const auto shards = BatchShards::plan(loop.batch_size, loop.accumulate, group, loop.name);
  const auto ckpt_dir = loop.out / "checkpoint";
  check_training_precision(loop.name, loop.precision);
  model.to(loop.device);
  const auto params = model.parameters();
  torch::optim::AdamW opt(params, torch::optim::AdamWOptions(loop.lr).weight_decay(loop.weight_decay));
  int64_t start = 0;
  if (checkpoint_exists(ckpt_dir)) {
    start = resume_with_adamw(ckpt_dir, model, loop.prefix, opt);
    LOG_INFO(loop.name, ": resumed from ", ckpt_dir.string(), " at step ", start);
  }
  group.check_same(loop.name + " start step", std::to_string(start));
  group.broadcast_from_main(model);
  model.train();

  LoopOptions options;
  options.name = loop.name;
  options.steps = loop.steps;
  options.time_budget_s = loop.time_budget_s;
  options.save_every = loop.save_every;
  options.loss_curve = loop.out / "loss.csv";
  options.columns = {"loss", "lr"};
  options.columns.insert(options.columns.end(), loop.extra_columns.begin(), loop.extra_columns.end());
  options.unit = loop.unit;
  std::deque<double> recent;
  const auto run = run_training_loop(
      options, start,
      [&](const LoopStep& s) {
        const double warm = std::min(1.0, static_cast<double>(s.index + 1) /
                                              static_cast<double>(std::max<int64_t>(1, loop.warmup_steps)));
        const double progress = std::min(
            1.0, static_cast<double>(s.index) / static_cast<double>(std::max<int64_t>(1, loop.steps)));
        const double lr = loop.lr * warm * (loop.cosine ? 0.1 + 0.45 * (1 + std::cos(M_PI * progress)) : 1.0);
        for (auto& group : opt.param_groups())
          static_cast<torch::optim::AdamWOptions&>(group.options()).lr(lr);
        opt.zero_grad();
        // This rank's micro-batches of the step; each draws its batch and noise from its own
        // (seed, stream index), so the split does not change what the whole world trains on.
        double loss_sum = 0;
        int64_t items = 0;
        std::vector<double> extra;
        for (int64_t j = 0; j < shards.accumulate; ++j) {
          auto gen = step_generator(loop.seed, shards.stream_index(s.index, j));
          AdamwStep r;
          {
            AutocastGuard autocast(loop.device.type(), loop.precision);
            r = step(s, shards.micro_batch, gen);
          }
          (shards.accumulate == 1 ? r.loss : r.loss / static_cast<double>(shards.accumulate)).backward();
          loss_sum += r.loss.item<double>();
          items += r.items;
          if (extra.empty()) extra.assign(r.extra.size(), 0.0);
          for (size_t e = 0; e < r.extra.size() && e < extra.size(); ++e)
            extra[e] += r.extra[e] / static_cast<double>(shards.accumulate);
        }
        group.average_gradients(params);
        opt.step();
        const double value = group.mean({loss_sum / static_cast<double>(shards.accumulate)})[0];
        recent.push_back(value);
        if (recent.size() > 20) recent.pop_front();
        if (after_step && group.main()) after_step(s.index + 1);
        std::vector<double> values = {value, lr};
        values.insert(values.end(), extra.begin(), extra.end());
        std::ostringstream note;
        note << "loss " << value;
        return StepRecord{values, items * shards.world, note.str()};
      },
      [&](int64_t steps_done, bool) { save_with_adamw(ckpt_dir, checkpoint(), opt, model, steps_done); });
  AdamwRun out;
  out.start_step = run.start_step;
  out.end_step = run.end_step;
  out.loss = recent.empty() ? std::nan("") : 0.0;
  for (double v : recent) out.loss += v / static_cast<double>(recent.size());
  out.seconds = run.seconds;
  out.items_per_second = run.items_per_second;
  return out;
}

MixtureIndex::MixtureIndex(std::vector<int64_t> sizes, std::vector<double> weights)
    : sizes_(std::move(sizes)), weights_(std::move(weights)) {
  DOJO_CHECK(weights_.empty() || weights_.size() == sizes_.size(),
             "mixture: " + std::to_string(weights_.size()) + " weights for " + std::to_string(sizes_.size()) +
                 " datasets");
  int64_t total = 0;
  for (const auto size : sizes_) offsets_.push_back(total), total += size;
  DOJO_CHECK(total > 0, "mixture: no clips in any dataset");
  double sum = 0;
  for (size_t d = 0; d < weights_.size(); ++d) {
    DOJO_CHECK(weights_[d] > 0, "mixture: dataset " + std::to_string(d) + " has weight " +
                                    std::to_string(weights_[d]) + "; weights must be positive");
    DOJO_CHECK(sizes_[d] > 0, "mixture: dataset " + std::to_string(d) + " is weighted but has no clips");
    sum += weights_[d];
  }
  double running = 0;
  for (const auto w : weights_) cumulative_.push_back(running += w / sum);
  if (!cumulative_.empty()) cumulative_.back() = 1.0;
}

torch::Tensor MixtureIndex::draw(int64_t count, torch::Generator& gen) const {
  const int64_t total = offsets_.back() + sizes_.back();
  if (weights_.empty()) return torch::randint(total, {count}, gen, torch::kLong);
  const auto pick = torch::rand({count}, gen, torch::kDouble);
  const auto within = torch::rand({count}, gen, torch::kDouble);
  auto index = torch::empty({count}, torch::kLong);
  auto out = index.accessor<int64_t, 1>();
  const auto p = pick.accessor<double, 1>(), w = within.accessor<double, 1>();
  for (int64_t i = 0; i < count; ++i) {
    const auto d = static_cast<size_t>(std::upper_bound(cumulative_.begin(), cumulative_.end() - 1, p[i]) -
                                       cumulative_.begin());
    const auto clip = std::min(sizes_[d] - 1, static_cast<int64_t>(w[i] * static_cast<double>(sizes_[d])));
    out[i] = offsets_[d] + clip;
  }
  return index;
}

std::vector<double> MixtureIndex::shares() const {
  std::vector<double> shares;
  const double total = static_cast<double>(offsets_.back() + sizes_.back());
  for (size_t d = 0; d < sizes_.size(); ++d)
    shares.push_back(weights_.empty() ? static_cast<double>(sizes_[d]) / total
                                      : cumulative_[d] - (d == 0 ? 0.0 : cumulative_[d - 1]));
  return shares;
}

nlohmann::json MixtureIndex::record(const std::vector<std::string>& names) const {
  DOJO_CHECK(names.size() == sizes_.size(), "mixture: " + std::to_string(names.size()) + " names for " +
                                                std::to_string(sizes_.size()) + " datasets");
  const auto share = shares();
  auto out = nlohmann::json::array();
  for (size_t d = 0; d < sizes_.size(); ++d)
    out.push_back({{"data", names[d]},
                   {"clips", sizes_[d]},
                   {"weight", weights_.empty() ? nlohmann::json(nullptr) : nlohmann::json(weights_[d])},
                   {"share", share[d]}});
  return out;
}

std::filesystem::path step_snapshot_dir(const std::filesystem::path& out, int64_t step) {
  char name[32];
  std::snprintf(name, sizeof(name), "step-%06lld", static_cast<long long>(step));
  return out / "snapshots" / name;
}

std::vector<std::filesystem::path> list_step_snapshots(const std::filesystem::path& out) {
  std::set<std::filesystem::path> found;
  if (std::filesystem::exists(out / "snapshots"))
    for (const auto& entry : std::filesystem::directory_iterator(out / "snapshots")) {
      auto name = entry.path().filename().string();
      // A save interrupted between its renames leaves only NAME.dojo-old (core/checkpoint.h).
      if (name.size() > 9 && name.compare(name.size() - 9, 9, ".dojo-old") == 0) name.resize(name.size() - 9);
      const bool step_name = name.size() == 11 && name.rfind("step-", 0) == 0 &&
                             name.find_first_not_of("0123456789", 5) == std::string::npos;
      if (step_name && checkpoint_exists(out / "snapshots" / name)) found.insert(out / "snapshots" / name);
    }
  return {found.begin(), found.end()};
}

StepSnapshots::StepSnapshots(std::filesystem::path out, std::vector<int64_t> at,
                             std::function<CheckpointData()> checkpoint)
    : out_(std::move(out)), at_(std::move(at)), checkpoint_(std::move(checkpoint)) {}

bool StepSnapshots::kept(int64_t step) const { return std::count(at_.begin(), at_.end(), step) > 0; }

void StepSnapshots::save(int64_t step) const {
  save_checkpoint(step_snapshot_dir(out_, step), checkpoint_());
}

void StepSnapshots::before(bool resuming) const {
  if (!resuming && kept(0)) save(0);
}

void StepSnapshots::after_step(int64_t steps_done) const {
  if (kept(steps_done)) save(steps_done);
}

void StepSnapshots::at_end(int64_t end_step, int64_t steps) const {
  if (end_step == steps && data_parallel().main() && !checkpoint_exists(step_snapshot_dir(out_, end_step)))
    save(end_step);
}

WindowEnds window_ends(const torch::Tensor& which, int64_t frames, int64_t span) {
  std::vector<int64_t> episode, end;
  const auto take = which.to(torch::kBool).contiguous();
  const auto* selected = take.data_ptr<bool>();
  for (int64_t e = 0; e < take.numel(); ++e) {
    if (!selected[e]) continue;
    for (int64_t t = span - 1; t < frames; ++t) {
      episode.push_back(e);
      end.push_back(t);
    }
  }
  return {torch::tensor(episode, torch::kLong), torch::tensor(end, torch::kLong)};
}

}  // namespace dojo::train
