// `dojo distill`: the post-trained teacher into the causal few-step student (teacher
// trajectories, then the warm-up regression; train/distill.h).
#include <CLI/CLI.hpp>

#include <cstdio>
#include <filesystem>
#include <memory>

#include "cli/commands.h"
#include "cli/model_args.h"
#include "cli/options.h"
#include "core/error.h"
#include "core/log.h"
#include "core/runtime.h"
#include "train/distill.h"

namespace fs = std::filesystem;

namespace dojo::cli {
namespace {

struct DistillArgs {
  std::string stage = "warmup", init, teacher, tokenizer, split = "train", out;
  std::vector<std::string> data;
  int64_t steps = 1000, save_every = 200, hop = 4, max_clips = 0, window = 12, sink = -1;
  std::string sink_position = "window_edge";
  TrainingDeviceArgs device;
  int batch = 8, student_steps = 4, teacher_steps = 35, counterfactual_copies = 0, warmup_chunks = 1;
  int64_t lora_rank = 0, accumulate = 1;
  double lora_alpha = 32;
  std::string lora_targets = "q,k,v,o,mlp1,mlp2";
  double minutes = 0, lr = 1e-4, weight_decay = 0.1, grad_clip = 0.1, clean_context_share = 0,
         context_noise = 0;
  bool fp32_times = false, zero1 = false;
  std::string warmup_anchor = "latent";
  train::SelfForcingOptions self_forcing;
  uint64_t seed = 0;
};

int run_distill(DistillArgs a) {
  if (a.teacher.empty()) LOG_INFO("no --teacher: distilling the reference set's post-trained world model");
  resolve_models(a.teacher, a.tokenizer, nullptr);
  train::DistillJob job;
  a.device.set_in(job, "distill");  // before any work
  job.stage = train::parse_distill_stage(a.stage);
  job.init = a.init;
  job.self_forcing = a.self_forcing;
  if (a.lora_rank > 0) {
    job.lora.rank = a.lora_rank;
    job.lora.alpha = a.lora_alpha;
    try {
      job.lora.targets = models::LoraConfig::parse_targets(a.lora_targets);
    } catch (const Error& e) {
      throw UsageError(std::string("--lora-targets: ") + e.what());
    }
  }
  std::vector<WeightedData> data;
  for (const auto& d : a.data) data.push_back(parse_weighted_data(d));
  job.weights = mixture_weights(data);
  for (const auto& d : data) {
    train::LatentCacheSpec spec;
    spec.dataset = d.dir;
    spec.split = a.split;
    spec.tokenizer = a.tokenizer;
    spec.hop = a.hop;
    spec.max_clips = a.max_clips;
    job.data.push_back(spec);
  }
  job.teacher = a.teacher;
  job.out = a.out;
  job.student.window_frames = a.window;
  job.student.sink_frames = a.sink >= 0 ? a.sink : std::min<int64_t>(1, a.window);
  job.student.sink_position =
      a.sink_position == "absolute" ? infer::SinkPosition::kAbsolute : infer::SinkPosition::kWindowEdge;
  job.student.steps = a.student_steps;
  job.student.bf16_times = !a.fp32_times;
  job.student.schedule();  // validates the steps before any work
  job.trajectories.teacher_steps = a.teacher_steps;
  job.trajectories.query_steps = train::TrajectorySpec::query_steps_for(a.teacher_steps);
  job.trajectories.seed = a.seed;
  job.trajectories.counterfactual_copies = a.counterfactual_copies;
  job.trajectories.chunks = a.warmup_chunks;
  job.trajectories.reencode_anchor = a.warmup_anchor == "reencoded";
  job.clean_context_share = a.clean_context_share;
  job.context_noise = a.context_noise;
  job.zero1 = a.zero1;
  job.options.lr = a.lr;
  job.options.weight_decay = a.weight_decay;
  job.options.grad_clip = a.grad_clip;
  job.options.warmup_steps = 0;  // constant learning rate, as released
  job.batch_size = a.batch;
  job.accumulate = a.accumulate;
  job.steps = a.steps;
  job.time_budget_s = a.minutes * 60;
  job.save_every = a.save_every;
  job.seed = a.seed;
  job.matmul_threads = matmul_bound_command_threads("distill", job.device.is_cuda());
  const auto r = train::run_distillation(job);
  if (job.stage == train::DistillStage::kWarmup)
    std::printf(
        "distill warm-up: %lld steps on %lld teacher trajectories, loss %.4f -> %.4f, fixed-batch loss "
        "%.4f -> %.4f\n",
        static_cast<long long>(r.steps), static_cast<long long>(r.clips), r.first_loss, r.last_loss,
        r.fixed_batch_loss_start, r.fixed_batch_loss_end);
  else
    std::printf(
        "distill self-forcing: %lld iterations on %lld clips, generator loss %.4f, fixed-clip rollout latent "
        "MSE %.4f -> %.4f\n",
        static_cast<long long>(r.steps), static_cast<long long>(r.clips), r.last_loss,
        r.fixed_batch_loss_start, r.fixed_batch_loss_end);
  std::printf("student %s/checkpoint (stream it with `dojo wm stream -c %s/checkpoint`)\n", a.out.c_str(),
              a.out.c_str());
  return 0;
}

}  // namespace

void register_distill(CLI::App& app) {
  auto a = std::make_shared<DistillArgs>();
  auto* cmd = app.add_subcommand(
      "distill",
      "Distill a post-trained world model into the causal 4-step student (trajectories + warm-up)");
  cmd->add_option("--stage", a->stage,
                  "warmup (regress the teacher's ODE points) | self-forcing (DMD, needs --init)")
      ->capture_default_str();
  cmd->add_option(
      "--init", a->init,
      "self-forcing: the warmed-up student checkpoint; warmup: start from this student of the same "
      "teacher instead of the teacher (a second warm-up on other trajectories, a fresh optimizer)");
  cmd->add_option("--teacher", a->teacher, "Post-trained world model (default: the reference set's)");
  cmd->add_option("--tokenizer", a->tokenizer, "Its tokenizer (default with the reference set: its own)");
  add_data_option(cmd, a->data,
                  "DIR:WEIGHT draws that dataset's clips in proportion to WEIGHT (a dataset without one "
                  "weighs 1); with no weight anywhere every clip is drawn alike")
      ->required();
  add_split_option(cmd, a->split);
  add_out_option(cmd, a->out, "directory: checkpoint/, trajectories/, loss.csv")->required();
  cmd->add_option("--steps", a->steps, "Warm-up steps (a resumed run continues up to this)")
      ->capture_default_str();
  cmd->add_option("--minutes", a->minutes, "Wall-clock budget, trajectories included (0: none)");
  cmd->add_option("--batch,-b", a->batch, "Trajectories per step")->capture_default_str();
  add_accumulate_option(cmd, a->accumulate);
  cmd->add_option("--lr", a->lr, "AdamW learning rate (constant; released: 3e-5 for a 2B net)")
      ->capture_default_str();
  cmd->add_option("--weight-decay", a->weight_decay, "AdamW weight decay")->capture_default_str();
  cmd->add_option("--grad-clip", a->grad_clip, "Global gradient-norm clip")->capture_default_str();
  cmd->add_option("--window", a->window,
                  "Earlier latent frames a new frame attends to (paper: 12, released: 3)")
      ->check(CLI::Range(int64_t{0}, int64_t{64}))
      ->capture_default_str();
  cmd->add_option("--sink-frames", a->sink,
                  "Latent frames from the start (the real first frame first) the student keeps in its "
                  "window for good, an attention sink; 0: none, as released (default: 1, 0 with --window 0)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--sink-position", a->sink_position,
                  "Where the sink sits in time: window_edge (the window's oldest slots) or absolute")
      ->check(CLI::IsMember({"window_edge", "absolute"}))
      ->capture_default_str();
  cmd->add_option("--student-steps", a->student_steps, "Student hops per latent frame, 1-4")
      ->check(CLI::Range(1, 4))
      ->capture_default_str();
  cmd->add_flag("--fp32-times", a->fp32_times, "Exact student times instead of the released bf16 rounding");
  cmd->add_option("--teacher-steps", a->teacher_steps, "Teacher UniPC steps for the trajectories")
      ->capture_default_str();
  cmd->add_option("--lora", a->lora_rank,
                  "Train LoRA adapters of this rank instead of the student's weights (the rest, action MLPs "
                  "included, stays frozen; the critic trains in full); 0 = full distillation")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cmd->add_option("--lora-alpha", a->lora_alpha, "LoRA alpha: the adapters' scale is alpha / rank")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--lora-targets", a->lora_targets, "Adapted layers: q, k, v, o (attention), mlp1, mlp2")
      ->capture_default_str();
  cmd->add_option("--hop", a->hop, "Clip start stride in frames")->capture_default_str();
  cmd->add_option("--max-clips", a->max_clips, "Clips per dataset (0: all)")->capture_default_str();
  cmd->add_option("--save-every", a->save_every, "Checkpoint every N steps")->capture_default_str();
  auto& sf = a->self_forcing;
  cmd->add_option("--generator-lr", sf.generator_lr, "self-forcing: student learning rate")
      ->capture_default_str();
  cmd->add_option("--critic-lr", sf.critic_lr, "self-forcing: critic learning rate")->capture_default_str();
  cmd->add_option("--critic-steps", sf.critic_steps, "self-forcing: critic updates per student update")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--min-frames", sf.min_frames, "self-forcing: shortest rollout in latent frames")
      ->capture_default_str();
  cmd->add_option("--max-frames", sf.max_frames,
                  "self-forcing: longest rollout in latent frames (clips of 1 + 4 (N - 1))")
      ->capture_default_str();
  cmd->add_option("--counterfactual-copies", a->counterfactual_copies,
                  "warm-up: also solve each clip's teacher ODE this many more times with other clips' "
                  "actions (same first frame, same noise), so the targets depend on the actions")
      ->check(CLI::Range(0, 8))
      ->capture_default_str();
  cmd->add_option("--warmup-chunks", a->warmup_chunks,
                  "warm-up: teacher chunks chained per trajectory (1: 13 frames; 4: 49 frames, the "
                  "positions a streaming student reaches in an evaluation rollout)")
      ->check(CLI::Range(1, 8))
      ->capture_default_str();
  cmd->add_option("--warmup-anchor", a->warmup_anchor,
                  "warm-up with --warmup-chunks > 1: what each later teacher chunk starts from: the "
                  "previous chunk's last latent as it is (latent), or its last frame decoded and "
                  "encoded alone (reencoded), as the teacher's own rollouts start")
      ->check(CLI::IsMember({"latent", "reencoded"}))
      ->capture_default_str();
  cmd->add_option("--clean-context-share", a->clean_context_share,
                  "warm-up: share of clips trained on a clean context, as the student streams (frames "
                  "before a random frontier clean, the rest at random trajectory points)")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  cmd->add_option("--context-noise", a->context_noise,
                  "warm-up: Gaussian noise on the clean context frames after the first, level drawn "
                  "uniformly below this (the student streams on latents it made itself)")
      ->check(CLI::Range(0.0, 2.0))
      ->capture_default_str();
  cmd->add_flag("--zero1", a->zero1,
                "Under data parallelism, each process keeps 1/N of the AdamW moments of the student "
                "(and of the critic): ZeRO-1, the same weights as without (docs/distributed.md)");
  cmd->add_option("--counterfactual-share", sf.counterfactual_share,
                  "self-forcing: share of rollouts driven by another clip's actions")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  a->device.add_to(cmd);
  add_seed_option(cmd, a->seed);
  cmd->callback([a] { set_action([a] { return run_distill(*a); }); });
}

}  // namespace dojo::cli
