#include "train/wm_train.h"

#include <ATen/CPUGeneratorImpl.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <deque>
#include <map>
#include <optional>
#include <sstream>

#include "core/atomic_file.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/runtime.h"
#include "core/state_dict.h"
#include "data/actions.h"
#include "data/episode_source.h"
#include "data/multi_view.h"
#include "train/data_parallel.h"
#include "train/train_loop.h"
#include "train/train_util.h"

namespace fs = std::filesystem;

namespace dojo::train {

WmStage parse_wm_stage(const std::string& text) {
  if (text == "pretrain") return WmStage::kPretrain;
  if (text == "posttrain") return WmStage::kPosttrain;
  if (text == "scratch") return WmStage::kScratch;
  throw Error("unknown stage '" + text + "' (expected pretrain, posttrain or scratch)");
}

std::string to_string(WmStage stage) {
  switch (stage) {
    case WmStage::kPretrain:
      return "pretrain";
    case WmStage::kPosttrain:
      return "posttrain";
    case WmStage::kScratch:
      return "scratch";
  }
  return "?";
}

nlohmann::json WmTrainOptions::to_json() const {
  return {{"lr", lr},
          {"weight_decay", weight_decay},
          {"grad_clip", grad_clip},
          {"warmup_steps", warmup_steps},
          {"ema_sigma_rel", ema_sigma_rel},
          {"condition_noise", condition_noise},
          {"motion_weight", motion_weight},
          {"action_dropout", action_dropout},
          {"flow",
           {{"shift", flow.shift},
            {"high_sigma_prob", flow.high_sigma_prob},
            {"temporal_axis", flow.temporal_axis == diffusion::TemporalAxis::kTime ? "time" : "channel"},
            {"temporal_weight", flow.temporal_weight}}}};
}

WmTrainOptions WmTrainOptions::from_json(const nlohmann::json& j) {
  WmTrainOptions o;
  o.lr = j.value("lr", o.lr);
  o.weight_decay = j.value("weight_decay", o.weight_decay);
  o.grad_clip = j.value("grad_clip", o.grad_clip);
  o.warmup_steps = j.value("warmup_steps", o.warmup_steps);
  o.ema_sigma_rel = j.value("ema_sigma_rel", o.ema_sigma_rel);
  o.condition_noise = j.value("condition_noise", o.condition_noise);
  o.motion_weight = j.value("motion_weight", o.motion_weight);
  o.action_dropout = j.value("action_dropout", o.action_dropout);
  if (j.contains("flow")) {
    const auto& f = j["flow"];
    o.flow.shift = f.value("shift", o.flow.shift);
    o.flow.high_sigma_prob = f.value("high_sigma_prob", o.flow.high_sigma_prob);
    o.flow.temporal_weight = f.value("temporal_weight", o.flow.temporal_weight);
    const auto axis = f.value("temporal_axis", std::string("time"));
    DOJO_CHECK(axis == "time" || axis == "channel",
               "flow.temporal_axis must be time or channel (got " + axis + ")");
    o.flow.temporal_axis =
        axis == "time" ? diffusion::TemporalAxis::kTime : diffusion::TemporalAxis::kChannel;
  }
  return o;
}

namespace {

torch::Tensor condition_mask_like(const torch::Tensor& x0) {
  auto mask = torch::zeros({x0.size(0), 1, x0.size(2), x0.size(3), x0.size(4)}, x0.options());
  mask.select(2, 0).fill_(1);  // latent frame 0 is the clean conditioning frame
  return mask;                 // [B, 1, T, h, w]
}

struct FlowLoss {
  torch::Tensor total, mse;
};

// x0 and actions on the network's device. Only the network's forward runs under autocast; its
// velocity is taken back to float32 so the loss (and the start of the backward pass) is float32.
FlowLoss flow_loss(models::ActionDit& net, const WmTrainOptions& options, const torch::Tensor& clean,
                   const torch::Tensor& actions, torch::Generator gen, Precision precision) {
  const auto& flow = options.flow;
  auto x0 = clean;
  if (options.condition_noise > 0) {
    // Noise on the conditioning latent: rollouts condition on frames the model made itself, so
    // it learns not to copy every detail of its context (GameNGen's context noise, without the
    // level embedding). Drawn on the CPU like the rest, so a seed gives the same run anywhere.
    const auto level = torch::rand({x0.size(0), 1, 1, 1}, gen) * options.condition_noise;  // [B, 1, 1, 1]
    const auto eps = torch::randn({x0.size(0), x0.size(1), x0.size(3), x0.size(4)}, gen);
    x0 = clean.clone();
    x0.select(2, 0).add_((level * eps).to(x0.options()));
  }
  const auto noise = diffusion::sample_training_noise(x0, flow, gen);  // drawn on CPU, on x0's device
  const auto mask = condition_mask_like(x0);
  models::DitInputs in;
  in.timesteps = noise.timesteps.view({x0.size(0), 1});  // [B, 1]
  in.condition_mask = mask;
  in.actions = actions;
  if (options.action_dropout > 0) {
    const auto keep =
        (torch::rand({actions.size(0), 1, 1}, gen) >= options.action_dropout).to(actions.options());
    in.actions = actions * keep;  // [B, 4 (T - 1), A]: whole clips lose their actions
  }
  torch::Tensor v;  // [B, 16, T, h, w]
  {
    AutocastGuard autocast(x0.device().type(), precision);
    v = models::denoise_velocity(*net, in, noise.x_t, x0, noise.noise, mask);
  }
  v = v.to(torch::kFloat32);
  const auto weight =
      options.motion_weight > 0 ? diffusion::motion_weight(x0, options.motion_weight) : torch::Tensor();
  return {diffusion::flow_matching_loss(v, noise.target_velocity, flow, nullptr, weight),
          (v - noise.target_velocity).pow(2).mean()};
}

}  // namespace

WmTrainer::WmTrainer(models::ActionDit net, WmTrainOptions options, torch::Device device, Precision precision)
    : net_(std::move(net)), ema_(net_->config), options_(options), device_(device), precision_(precision) {
  check_training_precision("wm train", precision_);
  // Moved before the optimiser sees the parameters: Module::to swaps their data in place.
  net_->to(device_);
  ema_->to(device_);
  // Every data-parallel rank starts from rank 0's weights (a resumed run then loads the same
  // checkpoint everywhere).
  data_parallel().broadcast_from_main(*net_);
  // The EMA starts as an exact copy; it never trains.
  load_state_dict(*ema_, state_dict(*net_));
  ema_->eval();
  for (auto& p : ema_->parameters()) p.set_requires_grad(false);
  for (auto& p : net_->parameters())
    if (p.requires_grad()) params_.push_back(p);
  for (auto& item : net_->named_parameters())
    if (item.value().requires_grad()) ema_params_.push_back(ema_->named_parameters()[item.key()]);
  optimizer_ = std::make_unique<torch::optim::AdamW>(
      params_, torch::optim::AdamWOptions(options_.lr).weight_decay(options_.weight_decay));
  fused_ = std::make_unique<FusedAdamW>(*optimizer_, params_, ema_params_);
  auto& group = data_parallel();
  if (group.active() && group.overlaps_backward())
    overlap_ = std::make_unique<OverlappedGradientAverage>(
        params_, fused_->offsets(), fused_->flat_grad(), group.world(),
        [&group](const torch::Tensor& flat) { return group.start_sum(flat, "the gradient all-reduce"); });
  ema_gamma_ = diffusion::power_ema_gamma(options_.ema_sigma_rel);
}

double WmTrainer::lr_at(int64_t step) const {
  if (options_.warmup_steps <= 0) return options_.lr;
  return options_.lr *
         std::min(1.0, static_cast<double>(step + 1) / static_cast<double>(options_.warmup_steps));
}

WmStepStats WmTrainer::step(const torch::Tensor& x0, const torch::Tensor& actions,
                            torch::Generator generator) {
  return step(std::vector<MicroBatch>{{x0, actions, std::move(generator)}});
}

WmStepStats WmTrainer::step(const std::vector<MicroBatch>& micro_batches) {
  std::vector<torch::Tensor> mse(micro_batches.size());
  auto s = step_loss(
      [&](models::ActionDitImpl&, int64_t j) {
        const auto& m = micro_batches[j];
        const auto loss =
            flow_loss(net_, options_, m.x0.to(device_), m.actions.to(device_), m.generator, precision_);
        mse[j] = loss.mse.detach();
        return loss.total;
      },
      static_cast<int64_t>(micro_batches.size()));
  double mse_sum = 0;
  for (const auto& m : mse) mse_sum += m.item<double>();
  s.mse = data_parallel().mean({mse_sum / static_cast<double>(mse.size())})[0];
  s.temporal = options_.flow.temporal_weight > 0 ? (s.loss - s.mse) / options_.flow.temporal_weight : 0.0;
  return s;
}

WmStepStats WmTrainer::step_loss(const std::function<torch::Tensor(models::ActionDitImpl& net)>& loss_fn) {
  return step_loss([&](models::ActionDitImpl& net, int64_t) { return loss_fn(net); }, 1);
}

WmStepStats WmTrainer::step_loss(
    const std::function<torch::Tensor(models::ActionDitImpl& net, int64_t micro)>& loss_fn, int64_t count) {
  net_->train();
  WmStepStats s;
  s.lr = lr_at(steps_);
  fused_->zero_grad();
  double loss_sum = 0;
  for (int64_t j = 0; j < count; ++j) {
    const auto loss = loss_fn(*net_, j);
    if (overlap_ && j == count - 1) overlap_->arm();  // the last pass: buckets start as they fill
    // One micro-batch alone is backpropagated unscaled: the step is bit for bit the plain one.
    (count == 1 ? loss : loss / static_cast<double>(count)).backward();
    loss_sum += loss.item<double>();
  }
  auto& group = data_parallel();
  if (overlap_)
    overlap_->finish();
  else
    group.average_gradients(params_);
  // Clipping, AdamW and the EMA in one pass over flat buffers (fused_adamw.h).
  s.grad_norm = fused_->step(options_.grad_clip, s.lr, diffusion::power_ema_beta(steps_ + 1, ema_gamma_));
  ++steps_;
  s.loss = s.mse = group.mean({loss_sum / static_cast<double>(count)})[0];
  return s;
}

double WmTrainer::eval_loss(const torch::Tensor& x0, const torch::Tensor& actions, uint64_t seed) {
  torch::NoGradGuard no_grad;
  ema_->eval();
  // The held-out loss measures the plain objective: no conditioning noise, no weighting.
  WmTrainOptions plain = options_;
  plain.condition_noise = plain.motion_weight = plain.action_dropout = 0;
  return flow_loss(ema_, plain, x0.to(device_), actions.to(device_), cpu_generator(seed), precision_)
      .total.item<double>();
}

void WmTrainer::save(const fs::path& dir, const nlohmann::json& extra) const {
  // Weights and moments are float32 on every precision; only their device varies. (.to(kCPU)
  // of a CPU tensor is the tensor itself, so CPU checkpoints stay bit-exact.)
  auto cpu = [](const torch::Tensor& t) { return t.detach().to(torch::kCPU); };
  CheckpointData data = models::world_model_checkpoint(*ema_);  // inference loads the EMA weights
  // Sampling uses the time shift the network was trained with, unless told otherwise.
  data.config["sampler"] = {{"shift", options_.flow.shift}};
  data.config.update(config_extras_);
  TrainerState ts;
  ts.step = steps_;
  ts.extra = extra;
  ts.extra["options"] = options_.to_json();
  for (const auto& [name, t] : state_dict(*net_)) ts.tensors.emplace_back("train." + name, cpu(t));
  for (auto& t : adamw_state(*optimizer_, *net_)) ts.tensors.emplace_back(t.first, cpu(t.second));
  for (auto& t : capture_rng_state()) ts.tensors.push_back(std::move(t));
  data.trainer = ts;
  save_checkpoint(dir, data);
}

void WmTrainer::apply_zero1(bool requested) {
  auto& group = data_parallel();
  group.check_same("--zero1", requested ? "on" : "off");
  if (requested) shard_optimizer_state();
}

void WmTrainer::shard_optimizer_state() {
  auto& group = data_parallel();
  if (!group.active()) return;
  FusedAdamW::Collectives c;
  c.rank = group.rank();
  c.world = group.world();
  c.all_gather = [&group](const torch::Tensor& mine, const std::vector<torch::Tensor>& out) {
    group.all_gather_into(mine, out, "gathering the updated parameters (ZeRO-1)");
  };
  c.gather_to_main = [&group](const torch::Tensor& mine, const std::vector<torch::Tensor>& out) {
    group.gather_into_main(mine, out, "gathering the optimizer state for a checkpoint (ZeRO-1)");
  };
  fused_->shard(std::move(c));
}

void WmTrainer::gather_optimizer_state() { fused_->gather_state(); }

void WmTrainer::resume(const fs::path& dir) {
  auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  LoadOptions net_opts;
  net_opts.prefix = "net.";
  auto ema_weights = ckpt.model().tensors(/*copy=*/false);
  if (ckpt.has_adapter()) {  // LoRA: the adapters are kept apart from the base weights
    auto adapters = ckpt.adapter().tensors(/*copy=*/false);
    ema_weights.insert(ema_weights.end(), adapters.begin(), adapters.end());
  }
  load_state_dict(*ema_, ema_weights, net_opts);
  steps_ = ckpt.has_trainer_state() ? ckpt.step() : 0;
  DOJO_CHECK(ckpt.has_trainer_tensors(), dir.string() + ": no trainer_state.safetensors to resume from");
  const auto tensors = ckpt.trainer_tensors().tensors(/*copy=*/true);
  LoadOptions raw_opts;
  raw_opts.prefix = "train.";
  load_state_dict(*net_, tensors, raw_opts);
  load_adamw_state(*optimizer_, *net_, tensors);
  fused_->adopt_state();
  restore_rng_state(tensors);
}

namespace {

// Per robot action slot, the union of the ranges of the datasets that fill it.
nlohmann::json robot_action_ranges(const std::vector<data::DatasetInfo>& datasets) {
  std::map<std::string, data::ArrayStats> ranges;
  for (const auto& info : datasets) {
    if (info.action_slot.empty() || !info.action_stats) continue;
    const auto it = ranges.find(info.action_slot);
    ranges[info.action_slot] =
        it == ranges.end() ? *info.action_stats : data::union_range(it->second, *info.action_stats);
  }
  nlohmann::json out = nlohmann::json::object();
  for (const auto& [slot, stats] : ranges) out[slot] = stats.to_json();
  return out;
}

// The per-dimension action factors of a new network: the given scale (or unit-std
// standardisation) on the dimensions the robot datasets' actions occupy, the network's present
// factors elsewhere (so latent actions keep theirs).
std::vector<double> robot_action_scale(const WmTrainJob& job, const LatentClips& clips,
                                       const models::DitConfig& c) {
  auto scale =
      c.action_scale.empty() ? std::vector<double>(static_cast<size_t>(c.action_dim), 1.0) : c.action_scale;
  const auto rows = clips.actions.reshape({-1, clips.actions.size(-1)}).to(torch::kFloat64);  // [N * 12, 384]
  for (const auto& spec : job.data) {
    const auto source = data::open_dataset(spec.dataset, spec.open_options());
    const auto& slot_name = source->info().action_slot;
    if (slot_name.empty()) continue;  // action-free video
    const auto slot = data::slot_by_name(slot_name);
    const int64_t width = std::min<int64_t>(source->info().action_dim, slot.width());
    for (int64_t d = slot.begin; d < slot.begin + width; ++d) {
      double factor = job.action_scale;
      if (job.standardize_actions) {
        const double std = rows.select(1, d).std().item<double>();
        factor = std > 1e-6 ? 1.0 / std : 1.0;
      }
      scale[static_cast<size_t>(d)] = factor;
    }
    LOG_INFO("wm train: actions of ", spec.dataset.string(), " (slot ", slot_name, ") scaled by ",
             job.standardize_actions ? "1 / their standard deviation" : std::to_string(job.action_scale));
  }
  return scale;
}

}  // namespace

models::ActionDit with_lora_adapters(const models::ActionDit& base, const models::LoraConfig& lora) {
  auto config = base->config;
  config.lora = lora;
  models::ActionDit adapted(config);
  LoadOptions opts;
  opts.strict = false;  // the adapters are new; every base tensor must still be copied
  const auto report = load_state_dict(*adapted, state_dict(*base), opts);
  for (const auto& name : report.missing)
    DOJO_CHECK(models::is_lora_name(name), "--lora: '" + name + "' was not copied from the base network");
  return adapted;
}

void freeze_all_but_adapters(models::ActionDitImpl& net, bool train_action_mlps, const std::string& who) {
  int64_t trainable = 0, frozen = 0;
  for (auto& item : net.named_parameters()) {
    const bool train = models::is_lora_name(item.key()) ||
                       (train_action_mlps && item.key().rfind("action_embedder", 0) == 0);
    item.value().set_requires_grad(train);
    (train ? trainable : frozen) += item.value().numel();
  }
  LOG_INFO(who, " --lora: ", trainable, " trainable parameters (adapters",
           train_action_mlps ? " and action MLPs" : "", "), ", frozen, " frozen");
}

WmTrainResult run_wm_training(const WmTrainJob& job) {
  DOJO_CHECK(!job.data.empty(), "wm train: no dataset given");
  DOJO_CHECK(job.batch_size > 0, "wm train: batch size must be positive");
  check_training_precision("wm train", job.precision);  // before the (slow) latent caching
  TimeBudget budget(job.time_budget_s);
  fs::create_directories(job.out);
  const auto ckpt_dir = job.out / "checkpoint";

  // The network's own action normalisation, one range per robot action slot: the union of its
  // robot datasets' ranges (kept from the checkpoint when resuming), so the same motion gives the
  // same numbers whichever dataset it comes from, in training and in every later rollout.
  const bool resuming = checkpoint_exists(ckpt_dir);
  std::vector<data::DatasetInfo> infos;  // each dataset opened once
  nlohmann::json views = nullptr;        // the canvas of a multi-view run, recorded for rollouts
  for (const auto& spec : job.data) {
    const auto source = data::open_dataset(spec.dataset, spec.open_options());
    infos.push_back(source->info());
    if (const auto* tiled = dynamic_cast<const data::MultiViewSource*>(source.get())) {
      DOJO_CHECK(views.is_null() || views == tiled->tiling().to_json(),
                 spec.dataset.string() + ": its views tile another canvas than the first dataset's");
      views = tiled->tiling().to_json();
    }
  }
  // Post-training from a model already post-trained on every robot slot of these datasets continues
  // it (more or other robot data): its action layer and its action ranges stay, since new ranges
  // would move every action it has learned to read.
  // A pretrained model may record ranges too (robot data with --actions none): its action layer
  // never read robot actions, so a checkpoint that says it was pretrained is not continued.
  nlohmann::json init_ranges = nlohmann::json::object();
  if (!resuming && job.stage == WmStage::kPosttrain && !job.init.empty() && checkpoint_exists(job.init)) {
    const auto init = Checkpoint::open(resolve_checkpoint_dir(job.init));
    const bool pretrained = init.has_trainer_state() && init.trainer_extra().value("stage", "") == "pretrain";
    if (!pretrained) init_ranges = init.config().value("actions", init_ranges);
  }
  bool continuing = !init_ranges.empty(), robot_data = false;
  for (const auto& info : infos) {
    if (info.action_slot.empty()) continue;
    robot_data = true;
    if (!init_ranges.contains(info.action_slot)) continuing = false;
  }
  continuing = continuing && robot_data;
  const auto action_ranges = resuming ? Checkpoint::open(resolve_checkpoint_dir(ckpt_dir))
                                            .config()
                                            .value("actions", nlohmann::json::object())
                             : continuing ? init_ranges
                                          : robot_action_ranges(infos);
  auto& group = data_parallel();
  const auto shards = BatchShards::plan(job.batch_size, job.accumulate, group, "wm train");
  // Rank 0 encodes the latent caches; the other ranks read them once they are written.
  std::vector<LatentClips> sets;
  group.main_first("the latent caches", [&] {
    for (size_t i = 0; i < job.data.size(); ++i) {
      auto spec = job.data[i];
      const auto& slot = infos[i].action_slot;
      if (!slot.empty() && action_ranges.contains(slot))
        spec.action_stats =
            data::ArrayStats::from_json(action_ranges[slot], ckpt_dir.string() + ": actions." + slot);
      sets.push_back(
          load_or_build_latent_clips(spec, job.out / ("latents-" + std::to_string(i) + ".safetensors")));
    }
  });
  const auto clips = concat_latent_clips(sets);
  const int64_t n = clips.size();
  std::vector<int64_t> set_sizes;
  for (const auto& set : sets) set_sizes.push_back(set.size());
  const MixtureIndex mixture(set_sizes, job.weights);
  std::vector<std::string> names;
  for (const auto& spec : job.data) names.push_back(spec.dataset.string());
  const auto mixture_record = mixture.record(names);
  if (mixture.weighted()) LOG_INFO("wm train: mixture ", mixture_record.dump());
  const nlohmann::json checkpoint_extra = {
      {"stage", to_string(job.stage)}, {"clips", n}, {"mixture", mixture_record}};
  std::optional<ScopedThreads> matmul_bound;
  if (job.matmul_threads > 0) matmul_bound.emplace(job.matmul_threads);

  torch::manual_seed(job.seed);
  std::optional<models::ActionDit> net;
  if (resuming) {
    const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(ckpt_dir));
    net.emplace(models::DitConfig::from_json(ckpt.config().at("config")));
  } else if (job.stage == WmStage::kPosttrain) {
    DOJO_CHECK(!job.init.empty(), "wm train --stage posttrain needs --init (a pretrained checkpoint)");
    net.emplace(models::load_world_model(job.init));
    // A new action space: the first layer of both action MLPs starts afresh; everything else
    // (including fc2, which pretraining taught to speak adaLN) is fine-tuned.
    if (continuing)
      LOG_INFO("wm train: ", job.init.string(), " is post-trained on these action slots; continuing it");
    else
      (*net)->reinit_action_input_layer();
    if (job.lora.enabled()) *net = with_lora_adapters(*net, job.lora);
  } else if (job.lora.enabled()) {
    throw Error("wm train: LoRA adapts a pretrained network: use it with --stage posttrain");
  } else {
    net.emplace(job.model);
  }
  if (!resuming && (job.action_scale != 1.0 || job.standardize_actions))
    (*net)->config.action_scale = robot_action_scale(job, clips, (*net)->config);
  // LoRA post-training trains the adapters and the action MLPs (re-initialised for the new action
  // space, as the release does); the rest keeps the pretrained weights.
  if ((*net)->config.lora.enabled()) freeze_all_but_adapters(**net, /*train_action_mlps=*/true, "wm train");
  (*net)->recompute_blocks = job.checkpoint_activations;
  WmTrainer trainer(*net, job.options, job.device, job.precision);
  nlohmann::json extras = nlohmann::json::object();
  if (!action_ranges.empty()) extras["actions"] = action_ranges;
  if (!views.is_null()) extras["views"] = views;
  if (!extras.empty()) trainer.set_config_extras(extras);
  // Sharded before a resume adopts the saved moments: each rank then copies its slice only.
  trainer.apply_zero1(job.zero1);
  if (resuming) {
    trainer.resume(ckpt_dir);
    LOG_INFO("wm train: resumed from ", ckpt_dir.string(), " at step ", trainer.steps_done());
  }
  group.check_same("the step to resume from", std::to_string(trainer.steps_done()));

  // A fixed batch with fixed noise tracks progress without the noise of random batches.
  const int64_t probe = std::min<int64_t>(n, 16);
  const auto probe_idx = torch::linspace(0, static_cast<double>(n - 1), probe).to(torch::kLong);
  const auto probe_x0 = clips.latents.index_select(0, probe_idx);
  const auto probe_actions = clips.actions.index_select(0, probe_idx);
  const uint64_t probe_seed = job.seed + 12345;

  WmTrainResult result;
  result.clips = n;
  result.heldout_loss_start = trainer.eval_loss(probe_x0, probe_actions, probe_seed);

  LoopOptions loop;
  loop.name = "wm " + to_string(job.stage);
  loop.steps = job.steps;
  // The budget clock started before caching: what is left of it bounds the steps.
  if (job.time_budget_s > 0) loop.time_budget_s = std::max(1e-3, job.time_budget_s - budget.elapsed());
  loop.save_every = job.save_every;
  loop.loss_curve = job.out / "loss.csv";
  loop.columns = {"loss", "mse", "temporal", "grad_norm", "lr", "clips_per_s", "fixed_batch_loss"};
  const int64_t start_step = trainer.steps_done();
  std::deque<double> recent;
  auto recent_mean = [&] {
    double sum = 0;
    for (double v : recent) sum += v;
    return recent.empty() ? 0.0 : sum / static_cast<double>(recent.size());
  };
  const auto run = run_training_loop(
      loop, start_step,
      [&](const LoopStep& info) {
        // Batch and noise of step k depend on (seed, k) only, so a resumed run sees the same stream;
        // each micro-batch of the step draws from its own stream index (BatchShards).
        std::vector<WmTrainer::MicroBatch> micro;
        for (int64_t j = 0; j < shards.accumulate; ++j) {
          auto gen = step_generator(job.seed, shards.stream_index(info.index, j));
          const auto idx = mixture.draw(shards.micro_batch, gen);
          micro.push_back({clips.latents.index_select(0, idx), clips.actions.index_select(0, idx), gen});
        }
        const auto t0 = std::chrono::steady_clock::now();
        const auto s = trainer.step(micro);
        if (info.saves) trainer.gather_optimizer_state();  // every rank, before rank 0 saves
        const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        recent.push_back(s.loss);
        if (recent.size() > 20) recent.pop_front();
        // The mean of this run's first 20 losses (or of all of them in a shorter run).
        if (info.index + 1 - start_step == std::min<int64_t>(20, job.steps - start_step))
          result.first_loss = recent_mean();
        const double probe_loss = info.saves && group.main()
                                      ? trainer.eval_loss(probe_x0, probe_actions, probe_seed)
                                      : std::nan("");
        std::ostringstream note;
        note << "loss " << s.loss;
        return StepRecord{{s.loss, s.mse, s.temporal, s.grad_norm, s.lr, job.batch_size / secs, probe_loss},
                          job.batch_size,
                          note.str()};
      },
      [&](int64_t, bool) { trainer.save(ckpt_dir, checkpoint_extra); });
  // A job with no steps to run still leaves a checkpoint behind.
  if (run.end_step == run.start_step && !resuming && group.main()) trainer.save(ckpt_dir, checkpoint_extra);
  result.last_loss = recent_mean();
  if (result.first_loss == 0) result.first_loss = result.last_loss;
  result.steps = trainer.steps_done();
  result.heldout_loss_end = trainer.eval_loss(probe_x0, probe_actions, probe_seed);
  result.seconds = run.seconds;
  result.clips_per_second = run.items_per_second;
  const auto& lat = clips.latents;  // [N, 16, T, h, w]
  result.gflops = result.clips_per_second * 3 *
                  models::dit_forward_flops(trainer.net()->config, lat.size(2), lat.size(3), lat.size(4)) /
                  1e9;
  LOG_INFO("wm train: ", result.clips_per_second, " clips/s (", result.gflops, " GFLOP/s of matmul work)");
  const nlohmann::json summary = {
      {"stage", to_string(job.stage)},
      {"device", job.device.str()},
      {"precision", dojo::to_string(job.precision)},
      {"steps", result.steps},
      {"clips", n},
      {"first_loss", result.first_loss},
      {"last_loss", result.last_loss},
      {"fixed_batch_loss_start", result.heldout_loss_start},
      {"fixed_batch_loss_end", result.heldout_loss_end},
      {"seconds", result.seconds},
      {"clips_per_second", result.clips_per_second},
      {"gflops", result.gflops},
      {"step_ms", 1e3 * run.step_seconds},
      {"matmul_ms_alone", 1e3 * run.products_seconds_alone},
      {"roofline_fraction", run.roofline_fraction},
      {"processes", group.world()},
      {"accumulate", job.accumulate},
      {"zero1", job.zero1 && group.active()},
      {"optimizer_moment_mib_per_process", static_cast<double>(trainer.optimizer_moment_bytes()) / (1 << 20)},
      {"allreduce_buckets", trainer.overlap_stats().buckets},
      {"allreduce_buckets_started_in_backward", trainer.overlap_stats().started_in_backward},
      {"options", job.options.to_json()}};
  if (group.main()) write_file_atomic(job.out / "train_summary.json", summary.dump(2) + "\n");
  return result;
}

}  // namespace dojo::train
