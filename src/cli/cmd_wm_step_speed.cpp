// `dojo wm step-speed`: the training, sampling and streaming steps of one architecture timed on
// random weights; with --export, the files the Python reference replays (scripts/python_speed.sh).
#include <CLI/CLI.hpp>
#include <cstdio>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>

#include "cli/commands.h"
#include "cli/model_args.h"
#include "cli/options.h"
#include "core/runtime.h"
#include "recipes/step_speed.h"

namespace dojo::cli {
namespace {

struct StepSpeedArgs {
  recipes::StepSpeedOptions options;
  std::string size = "64x64", export_dir;
  int64_t window = -1;
  SinkArgs sink;
  bool json = false;
};

int run_step_speed(StepSpeedArgs& a) {
  auto& o = a.options;
  o.model = dit_architecture(o.arch, "--arch");
  std::tie(o.height, o.width) = parse_size(a.size);
  if (a.window >= 0) o.student.window_frames = a.window;
  a.sink.apply(o.student);
  o.export_dir = a.export_dir;
  // Matmul-bound like every DiT stage (core/runtime.h): one OpenMP thread beside OpenBLAS's own.
  ScopedThreads matmul_bound(matmul_bound_threads());
  const auto r = recipes::run_step_speed(o);
  if (a.json) {
    std::printf("%s\n", r.dump(2).c_str());
    return 0;
  }
  std::printf(
      "%s DiT, %lld parameters, %s, %d intra-op threads\n\n| step | ms (mean) | ms (p50) | rate |\n"
      "|---|---|---|---|\n",
      o.arch.c_str(), static_cast<long long>(r["parameters"].get<int64_t>()), a.size.c_str(),
      at::get_num_threads());
  const auto row = [&](const char* name, const nlohmann::json& s, const char* unit) {
    std::printf("| %s | %.2f | %.2f | %.2f %s/s |\n", name, s["ms_mean"].get<double>(),
                s["ms_p50"].get<double>(), s[std::string(unit) + "_per_second"].get<double>(), unit);
  };
  row("training step", r["train"], "clips");
  row("sampling step", r["sample"], "clips");
  row("streaming step", r["stream"], "frames");
  const auto& gemm = r["train"]["gemm"];
  std::printf(
      "\nTraining step's matrix products (%lld, %.2f GFLOP): %.1f ms in the step, %.1f ms alone (%.1f "
      "GFLOP/s, the step's roofline); the step runs at %.0f %% of it\n",
      static_cast<long long>(gemm["calls"].get<int64_t>()), gemm["gflop"].get<double>(),
      gemm["ms_in_place"].get<double>(), gemm["ms_alone"].get<double>(), gemm["gflops_alone"].get<double>(),
      100 * gemm["fraction_of_roofline"].get<double>());
  return 0;
}

}  // namespace

void register_wm_step_speed(CLI::App& wm) {
  auto a = std::make_shared<StepSpeedArgs>();
  auto& o = a->options;
  auto* cmd = wm.add_subcommand("step-speed",
                                "Time the training step, a sampling step and a streaming step on random "
                                "weights; --export writes what the Python reference replays");
  cmd->add_option("--arch", o.arch, "small | tiny | 2b | student_2b | 14b")->capture_default_str();
  cmd->add_option("--size", a->size, "Frame size HxW (latents are 8x smaller)")->capture_default_str();
  cmd->add_option("--latent-frames", o.latent_frames, "Latent frames per training / sampling clip")
      ->check(CLI::Range(2, 64))
      ->capture_default_str();
  cmd->add_option("--train-batch", o.train_batch, "Clips per training step")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--sample-batch", o.sample_batch, "Clips per sampling step")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--warmup", o.warmup, "Untimed steps of each kind")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cmd->add_option("--repeats", o.repeats, "Timed training and sampling steps")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--stream-steps", o.stream_steps, "Timed streaming steps (4 frames each)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--window", a->window, "Student window in latent frames (default 12, the demo's)");
  a->sink.add_options(cmd);
  cmd->add_flag(
      "--checkpoint-activations", o.checkpoint_activations,
      "Time the training step with activation checkpointing (blocks run again in the backward pass)");
  cmd->add_option("--export", a->export_dir,
                  "Write weights, inputs and outputs here for scripts/python_reference/step_speed.py");
  add_seed_option(cmd, o.seed);
  add_json_option(cmd, a->json);
  cmd->callback([a] { set_action([a] { return run_step_speed(*a); }); });
}

}  // namespace dojo::cli
