#include "cli/model_args.h"

#include <CLI/CLI.hpp>

#include <filesystem>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "data/episode_clip.h"
#include "data/multi_view.h"
#include "infer/streaming.h"
#include "infer/world_model.h"
#include "models/dit.h"
#ifdef DOJO_WITH_SIM
#include "sim/generate.h"
#endif

namespace fs = std::filesystem;

namespace dojo::cli {

void resolve_models(std::string& checkpoint, std::string& tokenizer, std::string* probe) {
  const auto reference = default_reference_dir();
  if (checkpoint.empty()) {
    DOJO_CHECK(fs::exists(reference / "wm_posttrain" / "config.json"),
               "no --checkpoint given and no reference model set at " + reference.string() +
                   " (train one with `dojo demo`, or set DOJO_REFERENCE)");
    checkpoint = (reference / "wm_posttrain").string();
    if (tokenizer.empty()) tokenizer = (reference / "tokenizer").string();
    LOG_INFO("using the reference world model ", checkpoint);
  }
  if (tokenizer.empty())
    throw UsageError("--tokenizer is required with a model other than the reference set");
  if (probe != nullptr && probe->empty() && fs::exists(reference / "probe" / "config.json"))
    *probe = (reference / "probe").string();
}

std::filesystem::path reference_student() {
  const auto dir = default_reference_dir() / "student";
  return fs::exists(dir / "config.json") ? dir : fs::path();
}

std::filesystem::path reference_fast_decoder() {
  const auto dir = default_reference_dir() / "fast_decoder";
  return fs::exists(dir / "config.json") ? dir : fs::path();
}

std::filesystem::path reference_model_fast_decoder(const std::string& given, bool tokenizer_given) {
  if (!given.empty()) return given;
  return tokenizer_given ? fs::path() : reference_fast_decoder();
}

std::string default_eval_data() {
#ifdef DOJO_WITH_SIM
  const auto dir = fs::temp_directory_path() / "dojo-heldout-robot";
  sim::GenerateOptions g;
  g.episodes = 8;
  g.val_fraction = 1.0;  // all "val"
  g.seed = 1001;
  sim::generate_dataset(dir, g);
  LOG_INFO("no --data: held-out DojoSim episodes in ", dir.string());
  return dir.string();
#else
  throw UsageError("--data is required (this build has no DojoSim to make episodes)");
#endif
}

void ModelArgs::add_options(CLI::App* cmd, const std::string& what) {
  add_checkpoint_option(cmd, checkpoint, what + " (default: the reference set, models/reference)");
  cmd->add_option("--tokenizer", tokenizer, "Tokenizer checkpoint (default with the reference set: its own)");
  add_data_option(cmd, data)->description(
      "Dataset directory (episode store, LeRobot, EgoDex or video folder); default: 8 held-out DojoSim robot "
      "episodes made on the spot");
  cmd->add_option(
      "--text-context", text_context,
      "The prompt embedding the model cross-attends to: a .pt file holding the tensor or a safetensors file "
      "with one tensor 'context', [L, C] (default: zeros, as DojoSim models are trained; "
      "docs/checkpoints.md)");
  cmd->add_option("--embodiment", embodiment,
                  "LeRobot data: the robot (gr1, g1, yam, agibot; human or none for video alone); auto reads "
                  "info.json's robot_type, never the path")
      ->capture_default_str();
  cmd->add_option("--camera", camera,
                  "LeRobot data: video key (default: the robot's camera, else the first)");
  cmd->add_option("--frame-stride", frame_stride,
                  "Take every Nth frame and action (default 0: the robot's released rate: GR-1 and G1 2, "
                  "YAM and AgiBot 4, else 1)")
      ->capture_default_str();
  cmd->add_option("--action-norm", action_norm,
                  "Raw actions normalised with the model's recorded range (model), the dataset's statistics "
                  "(dataset), or auto: the model's where it records one for the robot's slot")
      ->capture_default_str();
  cmd->add_option("--frame-size", frame_size, "Centre-crop and resize frames to HxW (default: as stored)");
  add_views_options(cmd, views, view_layout, "default: the views the checkpoint was trained with");
}

#ifndef DOJO_ENGINE_ONLY  // the engine-only build has no data layer and no command reading datasets
data::RolloutDataOptions ModelArgs::data_options() const {
  data::RolloutDataOptions o;
  o.open.embodiment = embodiment;
  o.open.camera = camera;
  o.open.views = views;
  o.open.view_layout = view_layout;
  if (views.empty() && !checkpoint.empty()) {
    const auto dir = resolve_checkpoint_dir(checkpoint);
    if (const auto tiling = data::views_of_config(Checkpoint::open(dir).config(), dir.string())) {
      o.open.views = tiling->cameras;
      o.open.view_layout = data::to_string(tiling->layout);
      LOG_INFO(dir.string(), ": trained on views ", tiling->to_json().dump(),
               "; --data is read the same way");
    }
  }
  if (frame_stride < 0) throw UsageError("--frame-stride must be positive (0: the robot's released rate)");
  o.frame_stride = frame_stride;
  try {
    o.normalization = data::parse_action_normalization(action_norm);
  } catch (const Error& e) {
    throw UsageError(std::string("--action-norm: ") + e.what());
  }
  if (!frame_size.empty()) {
    const auto [h, w] = parse_size(frame_size);
    if (h % 16 != 0 || w % 16 != 0)
      throw UsageError("--frame-size must be a multiple of 16, got " + frame_size);
    o.height = static_cast<int>(h);
    o.width = static_cast<int>(w);
  }
  return o;
}
#endif

void ModelArgs::add_sampler_options(CLI::App* cmd) {
  cmd->add_option("--steps", steps, "Sampler steps")->capture_default_str();
  cmd->add_option("--solver", solver, "unipc | euler")->capture_default_str();
  cmd->add_option("--shift", shift, "Sampler time shift (default: the one the checkpoint was trained with)");
  cmd->add_option("--action-guidance", action_guidance,
                  "Action guidance scale (1 = off; > 1 needs a model trained with --action-dropout)")
      ->capture_default_str();
  cmd->add_option("--concat", concat, "aligned | released (chunk joining)")->capture_default_str();
}

void ModelArgs::resolve(std::string* probe) {
  resolve_models(checkpoint, tokenizer, probe);
  if (data.empty()) data = default_eval_data();
}

void ModelArgs::resolve_student(std::string& fast_decoder, std::string* probe) {
  const bool reference = checkpoint.empty(), reference_tokenizer = tokenizer.empty();
  if (reference) {
    if (const auto student = reference_student(); !student.empty()) {
      checkpoint = student.string();
      if (tokenizer.empty()) tokenizer = (default_reference_dir() / "tokenizer").string();
      LOG_INFO("using the reference student ", checkpoint);
    }
  }
  resolve(probe);
  if (reference && fast_decoder.empty()) {
    fast_decoder = reference_model_fast_decoder(fast_decoder, !reference_tokenizer).string();
    if (!fast_decoder.empty()) LOG_INFO("decoding with the reference fast decoder ", fast_decoder);
  }
}

infer::SamplerOptions ModelArgs::sampler(const infer::WorldModel& model) const {
  auto s = model.trained_sampler();
  s.steps = steps;
  if (shift > 0) s.shift = shift;
  s.action_guidance = action_guidance;
  s.solver = infer::parse_solver(solver);
  return s;
}

models::DitConfig dit_architecture(const std::string& name, const std::string& flag) {
  if (name == "small") return models::DitConfig::small();
  if (name == "2b" || name == "released_2b") return models::DitConfig::released_2b();
  if (name == "14b" || name == "released_14b") return models::DitConfig::released_14b();
  if (name == "student_2b") return models::DitConfig::student_2b();
  if (name == "tiny") return models::DitConfig::golden_tiny();
  throw UsageError(flag + ": unknown architecture '" + name + "' (small, 2b, 14b, student_2b or tiny)");
}

void SinkArgs::add_options(CLI::App* cmd) {
  cmd->add_option("--sink-frames", frames,
                  "Keep the first N latent frames (the start frame first) in the student's window for "
                  "good, an attention sink (default: the student's; 0 off)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--sink-position", position,
                  "Where the sink sits in time: window_edge (in the window's oldest slots, as in "
                  "training) or absolute (its own frame index)")
      ->check(CLI::IsMember({"window_edge", "absolute"}));
}

void SinkArgs::apply(infer::StudentConfig& student) const {
  if (frames >= 0) student.sink_frames = frames;
  if (!position.empty())
    student.sink_position =
        position == "absolute" ? infer::SinkPosition::kAbsolute : infer::SinkPosition::kWindowEdge;
}

}  // namespace dojo::cli
