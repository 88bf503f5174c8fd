// `dojo policy train | reader | detector | eval`: policy evaluation in the world model against
// DojoSim. The pipeline is recipes/policy_eval.h; this file resolves the models and options.
#include <CLI/CLI.hpp>

#include <cstdio>
#include <memory>

#include "cli/commands.h"
#include "cli/options.h"
#include "cli/world_model_args.h"
#include "core/log.h"
#include "core/runtime.h"
#include "eval/metrics.h"
#include "recipes/policy_eval.h"
#include "serve/external_policy.h"

namespace dojo::cli {
namespace {

struct DetectorArgs {
  recipes::DetectorRun run;
  bool world_model = false;  // frames from the world model's replays, labels from DojoSim
  WorldModelArgs wm;
};

struct PolicyEvalArgs {
  recipes::PolicyEvalRun run;
  WorldModelArgs wm;
  bool sim_as_world_model = false;
  double external_timeout = 120;
};

int run_detector(DetectorArgs a) {
  // The world model's --device and --precision: its replays and the detector's training (in fp32
  // when the replays run in fp16, which no trainer trains in).
  const bool fp16 = parse_precision(a.wm.precision) == Precision::kFloat16;
  TrainingDeviceArgs{a.wm.device, fp16 ? "fp32" : a.wm.precision}.set_in(a.run, "policy detector");
  if (fp16) LOG_INFO("policy detector: replays in fp16, the detector trains in fp32");
  if (a.world_model) {
    a.run.world_model = resolve_world_model(a.wm, "policy detector");
    a.run.replay_threads =
        matmul_bound_command_threads("policy detector", parse_device(a.wm.device).is_cuda());
  }
  return recipes::train_detector(a.run).is_object() ? 0 : 1;
}

int eval_policies(PolicyEvalArgs a) {
  recipes::check_scenes_held_out(a.run);  // before the models are resolved: a refusal costs nothing
  if (!a.sim_as_world_model) a.run.world_model = resolve_world_model(a.wm, "policy eval");
  a.run.make_external = [timeout = a.external_timeout](const recipes::PolicySpec& spec) {
    serve::ExternalPolicyOptions o;
    o.name = spec.name;
    o.command = spec.command;
    o.timeout_s = timeout;
    return serve::make_external_policy(o);
  };
  ScopedThreads matmul_bound(
      matmul_bound_command_threads("policy eval", parse_device(a.wm.device).is_cuda()));
  const auto outcome = recipes::run_policy_eval(a.run);
  const auto& report = outcome.report;
  std::printf("%-20s %8s %12s\n", "policy", "DojoSim", outcome.world_model_name.substr(0, 12).c_str());
  for (size_t i = 0; i < report.rates.names.size(); ++i)
    std::printf("%-20s %8.3f %12.3f\n", report.rates.names[i].c_str(), report.rates.real[i],
                report.rates.world_model[i]);
  const auto agreement_line = [](const eval::PolicyAgreement& g, size_t n, const char* which) {
    std::printf("pearson r %.4f  mmrv %.4f  spearman %.4f  mean |gap| %.4f  (%zu policies%s)\n", g.pearson,
                g.mmrv, g.spearman, g.mean_abs_gap, n, which);
  };
  agreement_line(report.agreement, report.rates.names.size(), "");
  for (const auto& [names, which] : {std::pair{&outcome.held_out, ": those the detector never saw"},
                                     std::pair{&outcome.seen, ": those the detector learnt from"}}) {
    const auto rates = eval::rates_of(report.rates, *names);
    if (rates.names.size() >= 2 && rates.names.size() < report.rates.names.size())
      agreement_line(eval::policy_agreement(rates), rates.names.size(), which);
  }
  std::printf("episodes agreeing %.3f (open-loop replays %.3f); seconds per episode: DojoSim %.2f, %s %.2f\n",
              report.episode_agreement, report.open_loop_agreement, report.real_seconds_per_episode,
              outcome.world_model_name.c_str(), report.world_model_seconds_per_episode);
  if (!outcome.detector_line.empty()) std::printf("%s\n", outcome.detector_line.c_str());
  LOG_INFO("policy eval: ", outcome.report_json.string(), ", ", outcome.report_html.string());
  return 0;
}

}  // namespace

void register_policy(CLI::App& app) {
  auto* policy =
      app.add_subcommand("policy", "Policy evaluation: rank policies in the world model against DojoSim");
  policy->require_subcommand(1);

  auto t = std::make_shared<recipes::BcRun>();
  auto* train_cmd = policy->add_subcommand(
      "train",
      "Render expert demonstrations in DojoSim and train the behaviour-cloning policy (frame + last "
      "command -> 4 commands); snapshots along training are policies of graded quality (resumable)");
  train_cmd->add_option("--out", t->out, "Output directory")->capture_default_str();
  train_cmd->add_option("--episodes", t->episodes, "Demonstration episodes")
      ->check(CLI::Range(2, 1000000))
      ->capture_default_str();
  train_cmd->add_option("--frames", t->frames, "Frames per demonstration")
      ->check(CLI::Range(8, 100000))
      ->capture_default_str();
  train_cmd->add_option("--noise", t->noise, "Noise injected into the executed arm commands (rad)")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  train_cmd
      ->add_option("--seed", t->seed, "First demonstration scene seed (keep apart from the evaluation's)")
      ->capture_default_str();
  train_cmd->add_option("--steps", t->steps, "Training steps")
      ->check(CLI::Range(0, 10000000))
      ->capture_default_str();
  train_cmd->add_option("--batch", t->batch, "Batch size")->check(CLI::Range(1, 4096))->capture_default_str();
  add_accumulate_option(train_cmd, t->accumulate);
  train_cmd->add_option("--shift", t->shift, "Random frame translation in pixels (augmentation)")
      ->check(CLI::Range(0, 16))
      ->capture_default_str();
  train_cmd
      ->add_option("--snapshots", t->snapshots, "Steps whose weights are kept as policies (besides the last)")
      ->delimiter(',')
      ->capture_default_str();
  auto train_device = std::make_shared<TrainingDeviceArgs>();
  train_device->add_to(train_cmd);
  train_cmd->callback([t, train_device] {
    set_action([t, train_device] {
      train_device->set_in(*t, "policy train");
      return recipes::train_bc(*t).is_object() ? 0 : 1;
    });
  });

  auto r = std::make_shared<recipes::ReaderRun>();
  auto* reader_cmd = policy->add_subcommand(
      "reader",
      "Render demonstrator episodes in DojoSim labelled with the object's and the bin's positions and "
      "train the scene reader the reader policies plan from; snapshots are readers of graded quality "
      "(resumable)");
  reader_cmd->add_option("--out", r->out, "Output directory")->capture_default_str();
  reader_cmd->add_option("--episodes", r->episodes, "Labelled episodes")
      ->check(CLI::Range(2, 1000000))
      ->capture_default_str();
  reader_cmd->add_option("--frames", r->frames, "Control steps per episode (every second frame is labelled)")
      ->check(CLI::Range(2, 100000))
      ->capture_default_str();
  reader_cmd->add_option("--seed", r->seed, "First scene seed (keep apart from the evaluation's)")
      ->capture_default_str();
  reader_cmd->add_option("--steps", r->steps, "Training steps")
      ->check(CLI::Range(0, 10000000))
      ->capture_default_str();
  reader_cmd->add_option("--batch", r->batch, "Batch size")
      ->check(CLI::Range(1, 4096))
      ->capture_default_str();
  add_accumulate_option(reader_cmd, r->accumulate);
  reader_cmd
      ->add_option("--snapshots", r->snapshots, "Steps whose weights are kept as readers (besides the last)")
      ->delimiter(',')
      ->capture_default_str();
  reader_cmd->callback([r] { set_action([r] { return recipes::train_reader(*r).is_object() ? 0 : 1; }); });

  auto d = std::make_shared<DetectorArgs>();
  auto* detector = policy->add_subcommand(
      "detector", "Render labelled DojoSim episodes and train the success detector on them (resumable)");
  detector->add_option("--out", d->run.out, "Output directory")->capture_default_str();
  detector->add_option("--policies", d->run.policies, "Policy set JSON (default: the built-in 13)");
  detector->add_option("--scenes", d->run.scenes, "Scenes per policy")
      ->check(CLI::Range(2, 100000))
      ->capture_default_str();
  detector->add_option("--seed", d->run.seed, "First scene seed (use others than the evaluation's)")
      ->capture_default_str();
  detector->add_option("--steps", d->run.steps, "Training steps")
      ->check(CLI::Range(0, 10000000))
      ->capture_default_str();
  add_accumulate_option(detector, d->run.accumulate);
  detector->add_option("--frames", d->run.frames, "Frames each policy acts for (as `policy eval --frames`)")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  detector
      ->add_option("--settle-frames", d->run.settle_frames,
                   "Frames holding the last command (as `policy eval`)")
      ->check(CLI::Range(0, 100000))
      ->capture_default_str();
  detector
      ->add_option("--window", d->run.window,
                   "Frames one decision sees (default 3; a resumed detector keeps its own)")
      ->check(CLI::Range(1, 64));
  detector
      ->add_option("--stride", d->run.stride,
                   "Frames between a window's frames (default 1; > 1: the window spans more of the episode)")
      ->check(CLI::Range(1, 64));
  detector->add_flag("--world-model", d->world_model,
                     "Train on the world model's replays of the episodes (labels from DojoSim): the "
                     "detector then reads generated video as `policy eval` shows it");
  add_world_model_options(detector, d->wm);
  detector->callback([d] { set_action([d] { return run_detector(*d); }); });

  auto e = std::make_shared<PolicyEvalArgs>();
  auto* ev =
      policy->add_subcommand("eval",
                             "Run every policy closed loop in DojoSim and in the world model; Pearson r, "
                             "MMRV, Spearman, success gap; JSON + HTML (resumable)");
  ev->add_option("--out", e->run.out, "Output directory")->capture_default_str();
  add_world_model_options(ev, e->wm);
  ev->add_option(
      "--detector", e->run.detector,
      "Success detector (default: OUT/detector-world-model or OUT/detector, trained when missing)");
  ev->add_option("--detector-steps", e->run.detector_steps,
                 "Training steps when the detector is trained here")
      ->capture_default_str();
  ev->add_option("--detector-frames", e->run.detector_frames,
                 "What a detector trained here learns from: DojoSim's frames, or the world model's "
                 "replays of the same episodes (labels from DojoSim either way)")
      ->check(CLI::IsMember({"dojosim", "world-model"}))
      ->capture_default_str();
  ev->add_option("--policies", e->run.policies,
                 "Policy set JSON to evaluate instead of the vision-only set (behaviour-cloning and reader "
                 "policies)");
  ev->add_flag("--with-scripted", e->run.with_scripted,
               "Also evaluate the 13 scripted demonstrators (open loop; the detector learnt from them, so "
               "they are reported apart as seen)");
  ev->add_option("--detector-policies", e->run.detector_policies,
                 "Policy set JSON whose scripted policies a detector trained here learns from (default: "
                 "the 13 scripted demonstrators)");
  ev->add_option("--bc", e->run.bc,
                 "The behaviour-cloning snapshots of this `dojo policy train` run (default: OUT/bc, "
                 "trained when missing)");
  ev->add_flag("--no-bc", e->run.no_bc, "Leave the behaviour-cloning policies out");
  ev->add_option("--reader", e->run.reader,
                 "The scene-reader snapshots of this `dojo policy reader` run (default: OUT/reader, "
                 "trained when missing)");
  ev->add_flag("--no-reader", e->run.no_reader, "Leave the reader policies out");
  ev->add_option("--reader-steps", e->run.reader_steps,
                 "Training steps when the scene reader is trained here")
      ->capture_default_str();
  ev->add_option("--bc-steps", e->run.bc_steps,
                 "Training steps when the behaviour-cloning policy is trained here")
      ->capture_default_str();
  ev->add_option(
      "--external", e->run.external,
      "NAME=COMMAND: a policy in another process speaking the step protocol (docs/policy_eval.md); "
      "repeatable");
  ev->add_option("--external-timeout", e->external_timeout, "Seconds an external policy may take to answer")
      ->check(CLI::Range(1.0, 1e6))
      ->capture_default_str();
  ev->add_option("--scenes", e->run.scenes, "Scenes per policy")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  ev->add_option("--seed", e->run.seed, "First scene seed")->capture_default_str();
  ev->add_option("--frames", e->run.frames, "Frames each policy acts for")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  ev->add_option("--settle-frames", e->run.settle_frames,
                 "Frames holding the last command before success is read")
      ->check(CLI::Range(0, 100000))
      ->capture_default_str();
  ev->add_option("--videos", e->run.videos,
                 "Scenes per policy written as side-by-side videos (OUT/videos, in the report)")
      ->check(CLI::Range(0, 100000))
      ->capture_default_str();
  ev->add_flag("--sim-as-world-model", e->sim_as_world_model,
               "Plug DojoSim in as the world model too (checks the harness: r = 1, MMRV = 0)");
  ev->callback([e] { set_action([e] { return eval_policies(*e); }); });
}

}  // namespace dojo::cli
