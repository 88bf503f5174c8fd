// What the world-model commands (`wm rollout`, `wm stream`, `eval`) share: the model (the reference
// set by default), the data (held-out DojoSim episodes by default) and the teacher's sampler.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

namespace CLI {
class App;
}
namespace dojo::models {
struct DitConfig;
}
namespace dojo::data {
struct RolloutDataOptions;
}
namespace dojo::infer {
class WorldModel;
struct SamplerOptions;
struct StudentConfig;
}  // namespace dojo::infer

namespace dojo::cli {

// The given checkpoint and tokenizer, or the reference model set shipped in models/reference when
// no checkpoint is given (and its probe, when one is wanted and none given).
void resolve_models(std::string& checkpoint, std::string& tokenizer, std::string* probe);

// The reference set's distilled real-time student (<ref>/student, a world-model checkpoint
// directory) and the fast streaming decoder of its tokenizer (<ref>/fast_decoder); empty paths
// where the set has no such directory with a config.json.
std::filesystem::path reference_student();
std::filesystem::path reference_fast_decoder();
// The fast decoder of a model taken from the reference set: `given` when set; else the set's own,
// unless another tokenizer was given (the set's decoder reads only its tokenizer's latents).
std::filesystem::path reference_model_fast_decoder(const std::string& given, bool tokenizer_given);

// Without --data: held-out DojoSim robot episodes (seed 1001, never a training seed), generated
// once into the temporary directory and re-used.
std::string default_eval_data();

struct ModelArgs {
  std::string checkpoint, tokenizer, data;
  std::string text_context;  // --text-context: a safetensors file with the prompt embedding
  // How --data is read (data/episode_clip.h): --embodiment, --camera, --frame-stride, --action-norm,
  // --frame-size.
  std::string embodiment = "auto", camera, action_norm = "auto", frame_size;
  int frame_stride = 0;
  // --views / --view-layout: cameras tiled into one canvas; default: as the checkpoint records.
  std::vector<std::string> views;
  std::string view_layout = "side_by_side";
  int steps = 35;
  std::string solver = "unipc", concat = "aligned";
  double shift = 0;  // 0: the checkpoint's
  double action_guidance = 1;

  void add_options(CLI::App* cmd, const std::string& what = "the world model");
  void add_sampler_options(CLI::App* cmd);
  // The options above as the data layer takes them (the views the checkpoint was trained with
  // unless --views says otherwise); throws UsageError on a bad value.
  data::RolloutDataOptions data_options() const;
  // The defaults filled in.
  void resolve(std::string* probe);
  // As resolve(), for a model that is streamed: without --checkpoint the reference student where
  // the set has one (else its world model, as resolve()), and with the reference tokenizer its
  // fast decoder, where the set has one and `fast_decoder` is empty.
  void resolve_student(std::string& fast_decoder, std::string* probe);
  // The model's trained sampler with the options given on the command line.
  infer::SamplerOptions sampler(const infer::WorldModel& model) const;
};

// The DiT architectures the commands that build one accept, by name: small (DojoSim scale), 2b or
// released_2b, 14b or released_14b, student_2b (the causal student: 2B with a longer RoPE table),
// tiny (the golden fixtures'). Throws UsageError naming `flag` for any other name.
models::DitConfig dit_architecture(const std::string& name, const std::string& flag);

// --sink-frames / --sink-position for the commands that stream a student; -1 / empty keep the
// student's own settings.
struct SinkArgs {
  int frames = -1;
  std::string position;
  void add_options(CLI::App* cmd);
  void apply(infer::StudentConfig& student) const;
};

}  // namespace dojo::cli
