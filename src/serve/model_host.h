// The models a server hosts and the episodes it starts from. Models load once (in the
// background: /health answers 503 until they are in); every session gets its own Generator,
// which shares the model's weights and holds its own KV cache and decoder state. Sessions of one
// model take turns on it, one step at a time (the weights are shared, and on 2 cores parallel
// steps would only split the same cores).
#pragma once

#include <torch/torch.h>

#include <atomic>
#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/autocast.h"
#include "data/actions.h"
#include "data/episode_source.h"
#include "infer/generator.h"

namespace dojo::serve {

// One hosted model, as `dojo serve` names it.
struct ModelSpec {
  std::string name;       // what clients select: "student", "teacher", ...
  bool streaming = true;  // the real-time student (4 frames per step) or the teacher
  std::filesystem::path checkpoint, tokenizer;
  std::filesystem::path fast_decoder;  // student only; empty: the Wan decoder
  int teacher_steps = 0;               // teacher only: sampler steps a chunk (0: the trained sampler's)
  std::filesystem::path text_context;  // the prompt embedding (infer::load_text_context); empty: zeros
};

// A session's view of a model: frames in, actions in, frames out (infer/generator.h).
using Generator = infer::Generator;

// Where sessions start: a dataset's episodes (first frame and the command in force there).
struct StartFrame {
  torch::Tensor frame;     // [H, W, 3] uint8
  torch::Tensor baseline;  // [w] raw command at the frame, or undefined (human video, images)
  std::string episode;
};

class ModelHost {
 public:
  struct Options {
    std::vector<ModelSpec> models;
    std::filesystem::path data;  // start frames; may be empty (then clients upload images)
    std::string split = "val";
    data::OpenOptions open;  // how `data` is opened (LeRobot: the robot, never from the path; camera)
    torch::Device device = torch::kCPU;
    Precision precision = Precision::kFloat32;
    bool cuda_graphs = true;  // streaming models on CUDA replay their hops as CUDA graphs
  };
  explicit ModelHost(Options options);
  ~ModelHost();

  // Loads every model; throws dojo::Error naming the checkpoint on failure. ready() after.
  void load();
  bool ready() const { return ready_; }

  // {models: [{name, kind, frame size, actions per step, action slots}], embodiments, episodes}.
  nlohmann::json capabilities() const;
  // The name `model` refers to ("" = the first model's). Throws dojo::Error for an unknown name.
  std::string resolve(const std::string& model) const;
  // A fresh generator of `model` ("" = the first). Throws dojo::Error for an unknown name.
  std::unique_ptr<Generator> make_generator(const std::string& model) const;
  // Episode `id` of the split ("" = the first) at the model's frame size.
  StartFrame start_frame(const std::string& model, const std::string& episode) const;
  // An uploaded image, centre-cropped and resized to the model's frame size.
  torch::Tensor fit_image(const std::string& model, const torch::Tensor& image) const;
  // Turns raw commands into the model's layout: commands of the dataset's robot (normalised with
  // the model's range for its slot, else the dataset's statistics, so a converted released model,
  // which records no range, is driven in the robot's units), else of the one slot the model
  // records; empty when neither says what a command is.
  std::optional<data::ActionChunker> chunker(const std::string& model) const;
  // The range of those raw commands (live commands are clamped to it), when known.
  std::optional<data::ArrayStats> command_stats(const std::string& model) const;
  std::vector<std::string> episode_ids() const;
  const std::filesystem::path& data_dir() const { return options_.data; }
  const std::string& split() const { return options_.split; }
  // {H, W} of the model's frames: the dataset's, else 64x64.
  std::pair<int, int> frame_shape(const std::string& model) const;

 private:
  struct Hosted;
  const Hosted& find(const std::string& model) const;
  // The slot raw commands drive and their range (see chunker()).
  std::optional<std::pair<data::ActionSlot, data::ArrayStats>> commands(const Hosted& h) const;

  Options options_;
  std::vector<std::shared_ptr<Hosted>> hosted_;
  std::shared_ptr<const data::EpisodeSource> source_;
  std::vector<size_t> split_;
  std::atomic<bool> ready_{false};
};

}  // namespace dojo::serve
