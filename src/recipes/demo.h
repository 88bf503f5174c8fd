// `dojo demo` as a library recipe: the whole system on the built-in DojoSim world, on a laptop
// CPU, with no data or weights to download. DojoSim generates human and robot episodes; a small
// LAM learns latent actions from video alone; a small tokenizer learns the latent space; the
// world model is pretrained on human video with latent actions, post-trained on robot actions,
// rolled out on held-out and out-of-distribution episodes and scored against a copy-the-first-frame
// baseline. Everything lands in one directory with a self-contained HTML report. Every stage
// resumes: re-running after an interruption continues where it stopped.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>

namespace dojo::recipes {

struct DemoOptions {
  std::filesystem::path out = "dojo_demo";
  double minutes = 30;  // training budget over all stages
  int episodes = 32;    // human and robot training episodes each
  int eval_episodes = 8;
  int frames = 64;
  int sampler_steps = 35;
  uint64_t seed = 0;
  int workers = 0;
  std::string device = "cpu", precision = "fp32";  // world-model training and rollouts
  // Intra-op threads for the matmul-bound stages (LAM, world model, rollouts); 0: the runtime's
  // choice (core/runtime.h, matmul_bound_threads).
  int matmul_threads = 0;
};

struct DemoSummary {
  std::filesystem::path report;  // report.html
  double seconds = 0;
  std::string eval_table;  // markdown, one row per split
};

DemoSummary run_demo(const DemoOptions& options);

}  // namespace dojo::recipes
