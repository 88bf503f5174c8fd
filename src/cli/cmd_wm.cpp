// `dojo wm train|rollout` and `dojo eval`: the action-conditioned world model.
#include <CLI/CLI.hpp>

#include <algorithm>

#include <cstdio>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>

#include "cli/commands.h"
#include "cli/model_args.h"
#include "cli/options.h"
#include "core/atomic_file.h"
#include "core/autocast.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "core/runtime.h"
#include "data/action_rows.h"
#include "data/episode_clip.h"
#include "eval/lpips.h"
#include "eval/wm_eval.h"
#include "infer/streaming.h"
#include "infer/world_model.h"
#include "io/video.h"
#include "models/keypoint_probe.h"
#include "train/wm_train.h"

namespace fs = std::filesystem;

namespace dojo::cli {
namespace {

struct WmTrainArgs {
  std::string stage = "pretrain", actions, split = "train", tokenizer, lam, init, out, model = "small",
              temporal_axis = "time", device = "cpu", precision = "fp32", embodiment = "auto",
              view_layout = "side_by_side";
  std::vector<std::string> data, views;
  int64_t steps = 2000, save_every = 100, hop = 2, max_clips = 0, warmup = 100, lora_rank = 0;
  int batch = 8;
  int64_t accumulate = 1;
  bool checkpoint_activations = false;
  bool zero1 = false;
  double lora_alpha = 32;
  std::string lora_targets = "q,k,v,o,mlp1,mlp2";
  double minutes = 0, lr = 1.6e-4, weight_decay = 0.1, grad_clip = 0.1, temporal_weight = 0.1, shift = 5.0,
         action_scale = 1.0, condition_noise = 0, motion_weight = 0, action_dropout = 0;
  uint64_t seed = 0;
  bool absolute_actions = false, whole_clip_actions = false, standardize_actions = false;
};

void add_device_options(CLI::App* cmd, std::string& device, std::string& precision) {
  add_device_option(cmd, device);
  add_precision_option(cmd, precision);
}

int run_wm_train(const WmTrainArgs& a) {
  train::WmTrainJob job;
  job.device = parse_device(a.device);  // a CUDA request without CUDA fails here, before any work
  job.precision = parse_precision(a.precision);
  job.stage = train::parse_wm_stage(a.stage);
  const auto mode = train::parse_action_mode(
      !a.actions.empty() ? a.actions : (job.stage == train::WmStage::kPretrain ? "latent" : "dataset"));
  std::vector<WeightedData> data;
  for (const auto& d : a.data) data.push_back(parse_weighted_data(d));
  job.weights = mixture_weights(data);
  for (const auto& parsed : data) {
    train::LatentCacheSpec spec;
    spec.dataset = parsed.dir;
    spec.split = a.split;
    spec.embodiment = a.embodiment;
    spec.views = a.views;
    spec.view_layout = a.view_layout;
    spec.tokenizer = a.tokenizer;
    spec.lam = a.lam;
    spec.mode = mode;
    spec.hop = a.hop;
    spec.max_clips = a.max_clips;
    spec.relative_actions = !a.absolute_actions;
    job.data.push_back(spec);
  }
  job.out = a.out;
  job.init = a.init;
  job.model = dit_architecture(a.model, "--model");
  if (a.whole_clip_actions) job.model.whole_clip_actions = 12;
  job.options.lr = a.lr;
  job.options.weight_decay = a.weight_decay;
  job.options.grad_clip = a.grad_clip;
  job.options.warmup_steps = a.warmup;
  job.options.flow.temporal_weight = a.temporal_weight;
  job.options.flow.shift = a.shift;
  job.options.condition_noise = a.condition_noise;
  job.options.motion_weight = a.motion_weight;
  job.options.action_dropout = a.action_dropout;
  job.action_scale = a.action_scale;
  job.standardize_actions = a.standardize_actions;
  if (a.lora_rank > 0) {
    if (job.stage != train::WmStage::kPosttrain)
      throw UsageError("--lora adapts a pretrained network: use it with --stage posttrain and --init");
    job.lora.rank = a.lora_rank;
    job.lora.alpha = a.lora_alpha;
    try {
      job.lora.targets = models::LoraConfig::parse_targets(a.lora_targets);
    } catch (const Error& e) {
      throw UsageError(std::string("--lora-targets: ") + e.what());
    }
  }
  job.options.flow.temporal_axis =
      a.temporal_axis == "channel" ? diffusion::TemporalAxis::kChannel : diffusion::TemporalAxis::kTime;
  job.batch_size = a.batch;
  job.accumulate = a.accumulate;
  job.checkpoint_activations = a.checkpoint_activations;
  job.zero1 = a.zero1;
  job.steps = a.steps;
  job.time_budget_s = a.minutes * 60.0;
  job.save_every = a.save_every;
  job.seed = a.seed;
  job.matmul_threads = matmul_bound_command_threads("wm train", job.device.is_cuda());
  const auto r = train::run_wm_training(job);
  std::printf(
      "wm %s: %lld steps, loss %.4f -> %.4f, fixed-batch loss %.4f -> %.4f, %.1f clips/s, %lld cached clips\n"
      "checkpoint %s/checkpoint, loss curve %s/loss.csv\n",
      a.stage.c_str(), static_cast<long long>(r.steps), r.first_loss, r.last_loss, r.heldout_loss_start,
      r.heldout_loss_end, r.clips_per_second, static_cast<long long>(r.clips), a.out.c_str(), a.out.c_str());
  return 0;
}

struct RolloutArgs {
  ModelArgs model;
  std::string split = "val", episode, actions_file, out, device = "cpu", precision = "fp32";
  int chunks = 4;
  uint64_t seed = 0;
};

int run_rollout(RolloutArgs a) {
  const auto device = parse_device(a.device);
  a.model.resolve(nullptr);
  ScopedThreads matmul_bound(matmul_bound_command_threads("wm rollout", device.is_cuda()));
  auto model =
      infer::WorldModel::load(a.model.checkpoint, a.model.tokenizer, device, parse_precision(a.precision));
  if (!a.model.text_context.empty())
    model.set_text_context(infer::load_text_context(a.model.text_context), a.model.text_context);
  const data::RolloutData rollout_data(
      a.model.data, a.chunks,
      data::parse_action_ranges(model.action_ranges(), a.model.checkpoint + ": actions"),
      a.model.data_options());
  LOG_INFO("wm rollout: ", rollout_data.describe());
  const auto clip = rollout_data.read(rollout_data.find(a.split, a.episode));
  // Counterfactual: the episode's first frame with actions from a file: rows of the model's layout
  // (safetensors 'actions' [12 K, 384]) or raw commands in the robot's units (JSON rows).
  const bool counterfactual = !a.actions_file.empty();
  torch::Tensor actions = clip.actions;  // [12 K, 384]
  if (counterfactual && fs::path(a.actions_file).extension() == ".json") {
    const auto file = read_json_file(a.actions_file);
    const auto raw =
        data::action_rows_from_json(file.is_object() && file.contains("actions") ? file["actions"] : file,
                                    a.actions_file + ": actions");  // [12 K, w]
    actions = rollout_data.raw_to_rows(raw, clip.raw_baseline);
    DOJO_CHECK(actions.size(0) == clip.actions.size(0),
               a.actions_file + ": " + std::to_string(actions.size(0)) + " rows, --chunks " +
                   std::to_string(a.chunks) + " takes " + std::to_string(clip.actions.size(0)));
  } else if (counterfactual) {
    actions = eval::read_rollout_actions(a.actions_file);
  }
  const auto pred = model.rollout(clip.video.select(0, 0).unsqueeze(0), actions.unsqueeze(0), a.seed,
                                  a.model.sampler(model), infer::parse_concat_mode(a.model.concat))[0];
  if (counterfactual)
    io::write_video(a.out, pred, {});
  else
    io::write_comparison_video(a.out, {clip.video, pred}, {"ground truth", "world model"}, clip.fps);
  std::printf("rollout of %s (%lld frames) -> %s\n", clip.episode.c_str(),
              static_cast<long long>(pred.size(0)), a.out.c_str());
  return 0;
}

struct WmEvalArgs {
  ModelArgs model;
  std::string out, probe, fast_decoder, device = "cpu", precision = "fp32";
  std::vector<std::string> splits = {"val"};
  std::vector<std::string> lpips_weights;
  int chunks = 4, episodes = 16, videos = 4, batch = 4, video_scale = 4;
  uint64_t seed = 0;
  bool json = false, action_sensitivity = false, student = false;
  SinkArgs sink;
};

int run_wm_eval(WmEvalArgs a) {
  if (!a.student && (a.sink.frames >= 0 || !a.sink.position.empty()))
    throw UsageError("--sink-frames and --sink-position stream a student: add --student");
  const auto device = parse_device(a.device);
  if (a.student)
    a.model.resolve_student(a.fast_decoder, &a.probe);
  else
    a.model.resolve(&a.probe);
  // Rollouts are DiT sampling: 31.0 generated frames/s with one OpenMP thread, 12.6 with two
  // (2 cores, OpenBLAS pthreads; docs/benchmarks.md).
  ScopedThreads matmul_bound(matmul_bound_command_threads("eval", device.is_cuda()));
  auto model =
      infer::WorldModel::load(a.model.checkpoint, a.model.tokenizer, device, parse_precision(a.precision));
  if (!a.model.text_context.empty())
    model.set_text_context(infer::load_text_context(a.model.text_context), a.model.text_context);
  eval::WmEvalOptions o;
  o.chunks = a.chunks;
  o.data = a.model.data_options();
  o.max_episodes = a.episodes;
  o.batch = a.batch;
  o.sampler = a.model.sampler(model);
  o.concat = infer::parse_concat_mode(a.model.concat);
  o.seed = a.seed;
  o.videos = a.videos;
  o.video_scale = a.video_scale;
  o.action_sensitivity = a.action_sensitivity;
  if (!a.out.empty()) o.video_dir = fs::path(a.out) / "videos";
  std::optional<infer::StreamingEngine> student;
  if (a.student) {
    infer::StreamingEngine::Options so;
    so.device = device;
    so.precision = parse_precision(a.precision);
    if (!a.fast_decoder.empty()) so.fast_decoder = models::load_fast_decoder(a.fast_decoder);
    if (!a.model.text_context.empty()) so.text_context = infer::load_text_context(a.model.text_context);
    student.emplace(infer::StreamingEngine::load(a.model.checkpoint, a.model.tokenizer, so,
                                                 [&](infer::StudentConfig& s) { a.sink.apply(s); }));
    o.student = &*student;
  }
  std::optional<models::KeypointProbe> probe;
  if (!a.probe.empty()) {
    probe = models::load_keypoint_probe(a.probe);
    o.probe = &*probe;
  }
  eval::Lpips lpips;
  if (!a.lpips_weights.empty()) {
    std::vector<fs::path> files(a.lpips_weights.begin(), a.lpips_weights.end());
    lpips = eval::Lpips::load(files);
    o.lpips = &lpips;
  }
  std::vector<eval::WmEvalResult> results;
  nlohmann::json j = {
      {"checkpoint", a.model.checkpoint},
      {"tokenizer", a.model.tokenizer},
      {"sampler", a.student ? nlohmann::json{{"student", student->options().student.to_json()}}
                            : nlohmann::json{{"solver", a.model.solver},
                                             {"steps", a.model.steps},
                                             {"shift", o.sampler.shift}}},
      {"concat", a.model.concat},
      {"device", model.device().str()},
      {"precision", to_string(model.precision())},
      {"metrics",
       "PSNR/SSIM per frame (piq conventions) on the predicted frames (frame 0 excluded for every method; "
       "*_all_frames: the released protocol, frame 0 included), mean per video, then mean over videos"},
      {"splits", nlohmann::json::array()}};
  if (a.student) j["fast_decoder"] = a.fast_decoder;  // "": the Wan decoder
  for (const auto& s : a.splits) {
    results.push_back(eval::evaluate_world_model(model, a.model.data, s, o));
    j["splits"].push_back(results.back().to_json());
  }
  const auto table = eval::markdown_table(results);
  if (!a.out.empty()) {
    fs::create_directories(a.out);
    write_file_atomic(fs::path(a.out) / "metrics.json", j.dump(2) + "\n");
    write_file_atomic(fs::path(a.out) / "metrics.md", table);
  }
  if (a.json)
    std::printf("%s\n", j.dump(2).c_str());
  else
    std::printf("%s", table.c_str());
  return 0;
}

}  // namespace

void register_wm(CLI::App& app) {
  auto* wm = app.add_subcommand("wm", "Action-conditioned world model (DiT, rectified flow)");
  wm->require_subcommand(1);
  register_wm_stream(*wm);
  register_wm_speed(*wm);
#ifdef DOJO_WITH_SIM
  register_wm_step_speed(*wm);
#endif

  auto t = std::make_shared<WmTrainArgs>();
  auto* train_cmd =
      wm->add_subcommand("train", "Train on cached tokenizer latents: pretrain, posttrain or scratch");
  train_cmd
      ->add_option("--stage", t->stage, "pretrain (human video) | posttrain (robot, needs --init) | scratch")
      ->capture_default_str();
  add_data_option(train_cmd, t->data,
                  "DIR:WEIGHT draws that dataset in proportion to WEIGHT (a dataset without one weighs 1); "
                  "with no weight anywhere every cached clip is drawn alike")
      ->required();
  add_split_option(train_cmd, t->split);
  train_cmd
      ->add_option("--embodiment", t->embodiment,
                   "LeRobot data: the robot (gr1, g1, yam, agibot, human, none); auto reads info.json's "
                   "robot_type, never the path")
      ->capture_default_str();
  add_views_options(train_cmd, t->views, t->view_layout,
                    "recorded in the checkpoint, so its rollouts, evaluation and server tile the same views");
  train_cmd->add_option("--tokenizer", t->tokenizer, "Tokenizer checkpoint (dojo tokenizer train)")
      ->required();
  train_cmd->add_option("--lam", t->lam, "LAM checkpoint, for --actions latent");
  train_cmd->add_option(
      "--actions", t->actions,
      "dataset | latent | none | ground-truth (default: latent for pretrain, else dataset)");
  train_cmd->add_option("--init", t->init,
                        "Pretrained world-model checkpoint (posttrain; a post-trained one with the same "
                        "action slots is continued: its action layer and ranges kept)");
  add_out_option(train_cmd, t->out, "directory for checkpoint/, loss.csv and the latent caches")->required();
  train_cmd->add_option("--model", t->model, "Network size: small | 2b | 14b (or student_2b, tiny)")
      ->capture_default_str();
  train_cmd->add_option("--steps", t->steps, "Total optimiser steps")->capture_default_str();
  train_cmd->add_option("--minutes", t->minutes,
                        "Stop (and checkpoint) after this many minutes; 0 = no limit");
  train_cmd->add_option("--batch,-b", t->batch, "Clips per step")->capture_default_str();
  add_accumulate_option(train_cmd, t->accumulate);
  train_cmd->add_option("--lr", t->lr, "AdamW learning rate")->capture_default_str();
  train_cmd->add_option("--weight-decay", t->weight_decay, "AdamW weight decay")->capture_default_str();
  train_cmd->add_option("--grad-clip", t->grad_clip, "Global gradient-norm clip (0 = off)")
      ->capture_default_str();
  train_cmd->add_option("--warmup", t->warmup, "Linear learning-rate warm-up steps")->capture_default_str();
  train_cmd->add_option("--temporal-axis", t->temporal_axis, "Temporal-consistency loss axis: time | channel")
      ->check(CLI::IsMember({"time", "channel"}))
      ->capture_default_str();
  train_cmd->add_option("--temporal-weight", t->temporal_weight, "Temporal-consistency loss weight (0 = off)")
      ->capture_default_str();
  train_cmd
      ->add_option("--shift", t->shift, "Time shift of the noise levels (5 as released, for 60x80 latents)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  train_cmd
      ->add_option("--action-scale", t->action_scale,
                   "Factor on the robot action dimensions before the action MLPs (kept in the checkpoint)")
      ->capture_default_str();
  train_cmd
      ->add_option("--condition-noise", t->condition_noise,
                   "Largest std of noise added to the conditioning latent in training (0 = clean)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  train_cmd
      ->add_option("--motion-weight", t->motion_weight,
                   "Strength of the motion-weighted loss: moving latent positions weigh 1 + S * motion")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  train_cmd
      ->add_option("--action-dropout", t->action_dropout,
                   "Probability per clip of training without actions (enables --action-guidance)")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  train_cmd
      ->add_option(
          "--lora", t->lora_rank,
          "Post-train LoRA adapters of this rank instead of every weight (the action MLPs still train "
          "in full; the rest stays frozen); 0 = full post-training")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  train_cmd->add_option("--lora-alpha", t->lora_alpha, "LoRA alpha: the adapters' scale is alpha / rank")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  train_cmd
      ->add_option("--lora-targets", t->lora_targets, "Adapted layers: q, k, v, o (attention), mlp1, mlp2")
      ->capture_default_str();
  train_cmd->add_flag("--standardize-actions", t->standardize_actions,
                      "Scale each robot action dimension to unit standard deviation over the cached clips");
  train_cmd->add_option("--hop", t->hop, "Frames between cached clip starts")->capture_default_str();
  train_cmd->add_option("--max-clips", t->max_clips, "Cache at most this many clips per dataset (0 = all)");
  train_cmd->add_flag("--absolute-actions", t->absolute_actions,
                      "Ablation: normalised absolute actions instead of chunk-relative deltas");
  train_cmd->add_flag("--whole-clip-actions", t->whole_clip_actions,
                      "Ablation: one embedding of all 12 actions added to every frame (no per-frame chunks)");
  train_cmd->add_flag("--checkpoint-activations", t->checkpoint_activations,
                      "Keep only each block's inputs and run it again in the backward pass: far less "
                      "activation memory for about a third more compute (docs/distributed.md, Memory)");
  train_cmd->add_flag("--zero1", t->zero1,
                      "Under data parallelism, each process keeps 1/N of the AdamW moments (ZeRO-1; "
                      "same parameters bit for bit; docs/distributed.md, Memory)");
  train_cmd->add_option("--save-every", t->save_every, "Checkpoint interval in steps")->capture_default_str();
  add_seed_option(train_cmd, t->seed);
  add_device_options(train_cmd, t->device, t->precision);
  train_cmd->callback([t] { set_action([t] { return run_wm_train(*t); }); });

  auto r = std::make_shared<RolloutArgs>();
  auto* roll = wm->add_subcommand("rollout", "Roll the model out from an episode's first frame and actions");
  r->model.add_options(roll);
  add_split_option(roll, r->split);
  roll->add_option("--episode", r->episode, "Episode id (default: the first episode of --split)");
  roll->add_option("--actions", r->actions_file,
                   "Counterfactual actions: a JSON file of 12 K rows of raw commands in the robot's units "
                   "([[...], ...] or {\"actions\": [...]}), or a safetensors file with 'actions' [12 K, 384] "
                   "already in the model's layout");
  roll->add_option("--chunks", r->chunks, "Chunks of 12 actions")->capture_default_str();
  r->model.add_sampler_options(roll);
  add_seed_option(roll, r->seed);
  add_out_option(roll, r->out, "mp4 file")->required();
  add_device_options(roll, r->device, r->precision);
  roll->callback([r] { set_action([r] { return run_rollout(*r); }); });

  auto e = std::make_shared<WmEvalArgs>();
  auto* ev =
      app.add_subcommand("eval", "Evaluate a world model: PSNR/SSIM of rollouts vs ground truth per split");
  e->model.add_options(ev);
  add_split_option(ev, e->splits);
  ev->add_option("--chunks", e->chunks, "Chunks of 12 actions per video (4 = the paper's 49 frames)")
      ->capture_default_str();
  ev->add_option("--episodes,-n", e->episodes, "Episodes per split (0 = all)")->capture_default_str();
  e->model.add_sampler_options(ev);
  ev->add_option("--batch,-b", e->batch, "Episodes rolled out together")->capture_default_str();
  ev->add_option("--videos", e->videos, "Side-by-side videos per split (with --out)")->capture_default_str();
  add_seed_option(ev, e->seed);
  add_out_option(ev, e->out, "directory for metrics.json, metrics.md and videos/");
  ev->add_option("--probe", e->probe,
                 "Keypoint probe checkpoint (dojo probe train): adds keypoint error and detection rate "
                 "(default: the reference set's, when present)");
  ev->add_flag(
      "--student", e->student,
      "The checkpoint is a distilled student (dojo distill): roll out by streaming it, 4 frames a step "
      "(without --checkpoint: the reference set's student, else its world model)");
  ev->add_option("--fast-decoder", e->fast_decoder,
                 "With --student: decode with this fast streaming decoder (default with the reference set: "
                 "its own, when it has one)");
  e->sink.add_options(ev);
  ev->add_flag("--action-sensitivity", e->action_sensitivity,
               "Also roll out with shuffled and with zero actions: does the model use the actions?");
  ev->add_option("--video-scale", e->video_scale, "Enlarge the side-by-side videos this many times")
      ->check(CLI::Range(1, 16))
      ->capture_default_str();
  ev->add_option("--lpips-weights", e->lpips_weights,
                 "LPIPS-VGG weights (safetensors; see docs/evaluation.md); adds LPIPS to the metrics");
  add_json_option(ev, e->json);
  add_device_options(ev, e->device, e->precision);
  ev->callback([e] { set_action([e] { return run_wm_eval(*e); }); });
}

}  // namespace dojo::cli
