// Making a preference study (serve/study.h): rollouts of two or more models on the same episodes,
// rendered here, or clips made elsewhere.
#pragma once

#include <torch/torch.h>

#include <filesystem>
#include <string>
#include <vector>

#include "core/autocast.h"
#include "serve/study.h"

namespace dojo::serve {

struct StudyModel {
  std::string name;
  std::filesystem::path checkpoint;
  bool student = false;                // streams 4 frames per step; else the teacher's 12-frame chunks
  std::filesystem::path fast_decoder;  // student only; empty: the Wan decoder
};

struct StudyFromModels {
  std::filesystem::path dir;
  std::string name;
  std::vector<StudyModel> models;  // two or more
  std::filesystem::path tokenizer, data;
  std::string split = "val";
  int episodes = 6;  // the split's first N episodes
  int chunks = 2;    // 12 frames each: every clip has 1 + 12 * chunks frames
  uint64_t seed = 0;
  torch::Device device = torch::kCPU;
  Precision precision = Precision::kFloat32;
};

// Renders the ground truth and every model's rollout with the episode's recorded actions from the
// episode's first frame. Clips land under DIR/videos/ID/ (each written under a temporary name and
// renamed, so a rerun after a crash renders only what is missing); study.json is written last.
Study create_study_from_models(const StudyFromModels& options);

// A study over given clips: SOURCE/ID/truth.mp4 and SOURCE/ID/MODEL.mp4 for every model, copied
// into DIR/videos/. Throws dojo::Error naming the first missing file.
Study create_study_from_videos(const std::filesystem::path& dir, const std::filesystem::path& source,
                               const std::vector<std::string>& models, const std::string& name);

}  // namespace dojo::serve
