// Labelling action-free video with latent actions: the LAM's output, stored per episode, is what
// world-model pretraining reads in place of actions.
#pragma once

#include <cstdint>
#include <filesystem>

#include "models/lam.h"

namespace dojo::train {

struct LamLabelSummary {
  int64_t episodes = 0, pairs = 0;
  double seconds = 0;
};

// Writes out_dir/<episode id>.safetensors holding "z_mu" [T - 1, latent] for every episode of the
// dataset (out_dir defaults to DATASET/lam_latents), each file atomically; episodes whose file
// already exists are kept (re-running resumes).
LamLabelSummary label_lam_dataset(models::LatentActionModel& model, const std::filesystem::path& dataset,
                                  std::filesystem::path out_dir = {}, int64_t batch_pairs = 16);

}  // namespace dojo::train
