// Checkpoints: a directory holding
//   config.json                 the model's config (plain JSON)
//   model.safetensors           the weights; __metadata__.config repeats config.json compactly
//   trainer_state.json          optional, for resuming: {"step": N, "extra": {...}}
//   trainer_state.safetensors   optional: optimizer moments, EMA weights, RNG states ("rng.cpu")
//
// Crash safety. save_checkpoint(DIR) never modifies DIR in place:
//   1. write every file into a fresh sibling DIR.dojo-tmp-<pid> (each file fsynced), fsync it;
//   2. if DIR exists, rename DIR -> DIR.dojo-old;
//   3. rename DIR.dojo-tmp-<pid> -> DIR; fsync the parent;
//   4. remove DIR.dojo-old; fsync the parent.
// Whatever moment the process dies at, one of these holds:
//   - DIR exists: it is complete (old before step 2, new after step 3); leftovers are garbage;
//   - DIR is missing but DIR.dojo-old exists (died between steps 2 and 3): DIR.dojo-old is the
//     complete previous checkpoint.
// So readers resolve DIR as "DIR if it exists, else DIR.dojo-old" (resolve_checkpoint_dir), and
// the next save first repairs the state (renames DIR.dojo-old back, or deletes it when DIR is
// present) and removes temporaries left by dead processes. One writer per DIR at a time.
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <optional>

#include "core/safetensors.h"

namespace dojo {

struct TrainerState {
  int64_t step = 0;
  nlohmann::json extra = nlohmann::json::object();  // epoch, data cursor, hyper-parameters...
  NamedTensors tensors;                             // optimizer state, EMA, RNG ("rng.*")
};

struct CheckpointData {
  nlohmann::json config = nlohmann::json::object();
  NamedTensors model;
  // When set, model.safetensors is written from this stream instead of `model` (a converted
  // checkpoint larger than memory: each tensor is read, written and dropped in turn).
  std::optional<TensorStream> model_stream;
  Metadata model_metadata;  // extra __metadata__ entries for model.safetensors
  // LoRA adapters kept apart from the base weights (PEFT's layout): adapter_model.safetensors,
  // written with the rest of the directory. Empty: no such file.
  NamedTensors adapter;
  Metadata adapter_metadata;
  std::optional<TrainerState> trainer;  // absent: an inference-only checkpoint
};

// Writes DIR crash-safely (see above), replacing a previous checkpoint there. Refuses (dojo::Error)
// to replace an existing non-empty directory that holds neither config.json nor model.safetensors.
void save_checkpoint(const std::filesystem::path& dir, const CheckpointData& data);

// The directory to read for checkpoint DIR: DIR, or DIR.dojo-old after a save was interrupted
// between its two renames. Throws dojo::Error when neither exists.
std::filesystem::path resolve_checkpoint_dir(const std::filesystem::path& dir);
// Whether resolve_checkpoint_dir(dir) would find a checkpoint: what a trainer asks to resume.
bool checkpoint_exists(const std::filesystem::path& dir);
// The checkpoint a directory stands for: DIR/checkpoint when DIR is a training run that holds one,
// else DIR itself (what commands taking "a run or its checkpoint" read).
std::filesystem::path run_checkpoint(const std::filesystem::path& dir);
// Identifies a checkpoint's weights without hashing them (path, size and time of its
// model.safetensors): a retrained model changes size or time, so a run that recorded it (a cache,
// a journal) sees the change. DIR may also be a training run whose checkpoint is DIR/checkpoint.
// Null for an empty path; dojo::Error when there is no checkpoint.
nlohmann::json checkpoint_fingerprint(const std::filesystem::path& dir);

// A checkpoint opened for reading; the safetensors files are memory-mapped.
class Checkpoint {
 public:
  // Throws dojo::Error naming the file that is missing or malformed.
  static Checkpoint open(const std::filesystem::path& dir);

  const std::filesystem::path& dir() const { return dir_; }  // as resolved
  const nlohmann::json& config() const { return config_; }
  const SafetensorsFile& model() const { return *model_; }
  // adapter_model.safetensors: LoRA adapters beside the base weights (`dojo convert --lora keep`,
  // `wm train --lora`); absent in plain checkpoints.
  bool has_adapter() const { return adapter_.has_value(); }
  const SafetensorsFile& adapter() const;

  bool has_trainer_state() const { return trainer_json_.has_value(); }
  // The following throw dojo::Error when there is no trainer state.
  int64_t step() const;
  const nlohmann::json& trainer_extra() const;
  // trainer_state.safetensors; throws when the checkpoint has none.
  const SafetensorsFile& trainer_tensors() const;
  bool has_trainer_tensors() const { return trainer_tensors_.has_value(); }

 private:
  std::filesystem::path dir_;
  nlohmann::json config_;
  std::optional<SafetensorsFile> model_;
  std::optional<SafetensorsFile> adapter_;
  std::optional<nlohmann::json> trainer_json_;
  std::optional<SafetensorsFile> trainer_tensors_;
};

// RNG state of the default CPU generator ("rng.cpu") and of every CUDA device ("rng.cuda.N"),
// as U8 tensors to put into TrainerState::tensors.
NamedTensors capture_rng_state();
// Restores the generators from tensors named as above; names absent from `tensors` are skipped.
void restore_rng_state(const NamedTensors& tensors);

}  // namespace dojo
