// `dojo demo`: wires the demo recipe (recipes/demo.h) to the command line.
#include <CLI/CLI.hpp>

#include <cstdio>
#include <memory>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/error.h"
#include "recipes/demo.h"

namespace dojo::cli {

void register_demo(CLI::App& app) {
  auto* cmd =
      app.add_subcommand("demo",
                         "The whole pipeline on the built-in DojoSim world: generate data, train the LAM "
                         "and the world model (pretrain + post-train) on the shipped tokenizer, distill "
                         "the real-time student, roll out, evaluate, and write report.html");
  auto o = std::make_shared<recipes::DemoOptions>();
  auto out = std::make_shared<std::string>(o->out.string());
  auto reference = std::make_shared<std::string>();
  auto tokenizer = std::make_shared<std::string>();
  add_out_option(cmd, *out, "demo directory (datasets, models, report.html)")->capture_default_str();
  cmd->add_option("--minutes,-m", o->minutes,
                  "Share this many minutes between the training stages instead of their step budgets "
                  "(results then depend on the machine)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--lam-steps", o->lam_steps, "LAM training steps")->capture_default_str();
  cmd->add_option(
      "--tokenizer", *tokenizer,
      "Tokenizer checkpoint to use as is, as the paper uses Wan2.1's VAE pretrained (default: "
      "the reference set's, models/reference/tokenizer, when present); \"train\" to train one "
      "here (--tokenizer-steps; 13 more minutes on the 2-core reference machine, 31 on the slowest "
      "measured)");
  cmd->add_option("--tokenizer-steps", o->tokenizer_steps,
                  "Tokenizer training steps (with --tokenizer train)")
      ->capture_default_str();
  cmd->add_option("--probe-steps", o->probe_steps, "Keypoint probe training steps")->capture_default_str();
  cmd->add_option("--pretrain-steps", o->pretrain_steps, "World-model pretraining steps")
      ->capture_default_str();
  cmd->add_option("--posttrain-steps", o->posttrain_steps, "World-model post-training steps")
      ->capture_default_str();
  cmd->add_option("--warmup-steps", o->warmup_steps, "Student warm-up steps")->capture_default_str();
  cmd->add_option("--self-forcing-steps", o->self_forcing_steps,
                  "Student Self-Forcing iterations (0: none, the warmed-up student is the student)")
      ->capture_default_str();
  cmd->add_option("--fast-decoder-steps", o->fast_decoder_steps, "Fast streaming decoder steps")
      ->capture_default_str();
  cmd->add_option("--max-clips", o->max_clips,
                  "Clips per dataset in the latent caches (world model, student, fast decoder)")
      ->check(CLI::Range(int64_t{1}, int64_t{1000000}))
      ->capture_default_str();
  cmd->add_option("--stream-frames", o->stream_frames,
                  "Frames the student streams when its speed is timed (a multiple of 4)")
      ->check(CLI::Range(4, 100000))
      ->capture_default_str();
  cmd->add_option("--reference", *reference,
                  "Reference model set to evaluate beside the demo's models (default: models/reference when "
                  "present; \"none\" to skip)");
  cmd->add_option("--episodes,-n", o->episodes, "Training episodes per embodiment")
      ->check(CLI::Range(2, 100000))
      ->capture_default_str();
  cmd->add_option("--eval-episodes", o->eval_episodes, "Held-out episodes per evaluation split")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  cmd->add_option("--frames", o->frames, "Frames per episode (10 Hz; at least 50 for the 49-frame protocol)")
      ->check(CLI::Range(50, 100000))
      ->capture_default_str();
  cmd->add_option("--sampler-steps", o->sampler_steps, "UniPC steps per chunk")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  cmd->add_option("--eval-chunks", o->eval_chunks,
                  "12-frame chunks per evaluation rollout (4: the paper's 49 frames)")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  add_seed_option(cmd, o->seed);
  add_workers_option(cmd, o->workers);
  add_device_option(cmd, o->device);
  add_precision_option(cmd, o->precision);
  cmd->callback([cmd, o, out, reference, tokenizer] {
    set_action([cmd, o, out, reference, tokenizer] {
      o->out = *out;
      o->reference = *reference == "none" ? std::filesystem::path() : std::filesystem::path(*reference);
      if (reference->empty() && std::filesystem::exists(default_reference_dir() / "wm_posttrain"))
        o->reference = default_reference_dir();
      if (tokenizer->empty()) {
        const auto shipped = default_reference_dir() / "tokenizer";
        if (std::filesystem::exists(shipped / "config.json")) o->tokenizer = shipped;
      } else if (*tokenizer != "train") {
        o->tokenizer = *tokenizer;
      }
      if (!o->tokenizer.empty() && cmd->count("--tokenizer-steps") > 0)
        throw UsageError("demo: --tokenizer-steps trains a tokenizer: give --tokenizer train with it");
      o->matmul_threads = global_options().threads;  // an explicit --threads wins
      const auto s = recipes::run_demo(*o);
      std::printf("\nDreamDojo.cpp demo finished in %.1f min. Open %s in a browser.\n\n%s\n",
                  s.seconds / 60.0, s.report.string().c_str(), s.eval_table.c_str());
      std::printf(
          "Outputs in %s/: datasets (human/, robot*/), lam/, tokenizer/, probe/, wm_pretrain/, "
          "wm_posttrain/, "
          "rollouts/, eval.md, demo.json, stages/. Re-running re-uses finished stages.\n",
          o->out.string().c_str());
      return 0;
    });
  });
}

}  // namespace dojo::cli
