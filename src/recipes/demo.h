// `dojo demo` as a library recipe: the whole system on the built-in DojoSim world, on a laptop
// CPU, with no data or weights to download. DojoSim generates human and robot episodes; a small
// LAM learns latent actions from video alone; a small tokenizer gives the latent space (trained
// beforehand and copied in, as the paper takes Wan2.1's VAE pretrained, or trained here); a
// keypoint probe learns where the arm and the hand are; the world model is pretrained on human
// video with latent actions, post-trained on robot actions, rolled out on held-out,
// out-of-distribution and counterfactual episodes and scored against a copy-the-first-frame
// baseline, with and without the true actions; then distilled into the real-time student, which is
// scored the same way and timed streaming 600 frames. Everything lands in one directory with a
// self-contained HTML report.
//
// Reproducible: every stage has a budget in optimisation steps, so the same seed gives the same
// models on any machine (a --minutes budget remains as an option). Resumable: a finished stage
// records its settings (every input that changes its output: its options, the records of the
// stages it reads, the seed, and the device and precision it computes on) and its result in
// OUT/stages/<stage>.json, and is re-used when the demo runs again with the same settings; a stage
// whose settings changed runs again from scratch (its old outputs are discarded first), and an
// interrupted one resumes from its checkpoint.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>

namespace dojo::recipes {

struct DemoOptions {
  std::filesystem::path out = "dojo_demo";
  int episodes = 32;       // human and robot training episodes each (robot: plus the held-out ones)
  int eval_episodes = 8;   // per evaluation split
  int frames = 64;         // per episode, at 10 Hz
  int sampler_steps = 35;  // UniPC steps per chunk
  int eval_chunks = 4;     // 12-frame chunks per evaluation rollout: the paper's 49 frames
  uint64_t seed = 0;
  int workers = 0;
  std::string device = "cpu", precision = "fp32";  // world-model training and rollouts
  // Intra-op threads for the matmul-bound stages (LAM, world model, rollouts); 0: the runtime's
  // choice (core/runtime.h, matmul_bound_threads).
  int matmul_threads = 0;
  // Stage budgets in optimisation steps (with the tokenizer copied in: 27 minutes on the 2-core
  // reference machine, docs/benchmarks.md).
  int64_t lam_steps = 1500, tokenizer_steps = 2700, probe_steps = 600, pretrain_steps = 1200,
          posttrain_steps = 1500;
  // The real-time student: warm-up steps, Self-Forcing iterations (0: none, the warmed-up student is
  // the student), fast-decoder steps. Self-Forcing gave back part of the warm-up's held-out accuracy
  // in every run on the reference teacher (docs/benchmarks.md, "The reference student re-made").
  int64_t warmup_steps = 600, self_forcing_steps = 0, fast_decoder_steps = 400;
  // Warm-up chunks anchored on their predecessor's last frame decoded and encoded alone, as the
  // rollouts do, and this share of each batch trained on a clean context, as the student streams.
  // With 600 warm-up steps and no Self-Forcing, on the reference teacher and the demo's data: held-out
  // keypoint error 7.90 -> 6.96 px against 300 warm-up steps + 300 Self-Forcing iterations
  // (docs/benchmarks.md, "The reference student re-made").
  bool warmup_reencoded_anchors = true;
  double warmup_clean_context_share = 0.5;
  // Teacher chunks chained per warm-up trajectory: 4 covers the 49 frames an evaluation rollout
  // streams (held-out keypoint error of the reference teacher's student 9.15 -> 7.90 px with 1 -> 4,
  // docs/benchmarks.md, "A student that keeps following the actions after frame 12").
  int warmup_chunks = 4;
  // Clips per dataset in the latent caches of the world model, the student (whose teacher
  // trajectories are built on them) and the fast decoder.
  int64_t max_clips = 192;
  // Frames the student streams when timed at batch 1 (a multiple of 4).
  int stream_frames = 600;
  // Noise on the conditioning latent in post-training (wm train --condition-noise): held-out
  // keypoint error 9.2 -> 7.4 px at 1000 steps (docs/action_following.md).
  double posttrain_condition_noise = 0.3;
  // > 0: share this many minutes between the training stages instead (machine-dependent results).
  double minutes = 0;
  // A trained tokenizer checkpoint to copy in and use as is (the CLI's default: the reference set's);
  // empty: train one here for tokenizer_steps.
  std::filesystem::path tokenizer;
  // A reference model set (models/reference) to evaluate beside the demo's own models; empty:
  // none. Its tokenizer, probe and world model are used as a set.
  std::filesystem::path reference;
};

struct DemoSummary {
  std::filesystem::path report;  // report.html
  double seconds = 0;
  std::string eval_table;  // markdown
};

DemoSummary run_demo(const DemoOptions& options);

}  // namespace dojo::recipes
