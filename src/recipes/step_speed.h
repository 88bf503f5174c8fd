// `dojo wm step-speed`: the three steps users time against Python PyTorch, on random weights of
// one architecture: the teacher's training step (flow-matching forward, backward, clipping,
// AdamW, the power EMA), one step of the teacher's sampler (a velocity evaluation of a batch of
// clips, no gradient) and one streaming step of the student (4 hops over a KV cache and the clean
// pass that stores the new frame). With an export directory it also writes everything a Python
// reference needs to replay the same steps and check it computed the same numbers first: the
// weights, the inputs, the random-number seeds and the outputs (scripts/python_reference/).
#pragma once

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>

#include "infer/streaming.h"
#include "models/dit.h"

namespace dojo::recipes {

struct StepSpeedOptions {
  models::DitConfig model = models::DitConfig::small();
  std::string arch = "small";       // the name model came from, for the report
  int64_t height = 64, width = 64;  // pixels; latents are 8x smaller
  int64_t latent_frames = 4;        // per training / sampling clip (13 video frames)
  int64_t train_batch = 8;          // the demo's world-model batch
  int64_t sample_batch = 4;         // the demo's evaluation batch
  int64_t warmup = 3;               // untimed steps of each kind
  int64_t repeats = 20;             // timed training and sampling steps
  int64_t stream_steps = 40;        // timed streaming steps
  // The demo's student: a window of 12 latent frames with the start frame kept as a sink.
  infer::StudentConfig student = [] {
    infer::StudentConfig s;
    s.window_frames = 12;
    s.sink_frames = 1;
    return s;
  }();
  uint64_t seed = 0;
  bool checkpoint_activations = false;  // the training step with activation checkpointing
  std::filesystem::path export_dir;     // empty: time only
};

// Runs the three kinds of step and returns the report: per kind the step times (mean, p50, min in
// ms) and throughput, the configuration, and the machine (version_info). Writes the export first
// when asked, from the same weights and draws the timed steps use.
nlohmann::json run_step_speed(const StepSpeedOptions& options);

}  // namespace dojo::recipes
