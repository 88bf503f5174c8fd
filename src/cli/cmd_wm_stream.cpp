// `dojo wm stream`: the real-time student, one latent frame (4 video frames) per step, from a
// start frame and a stream of actions (a file, stdin, or an episode's recording) to an mp4 or raw
// frames on stdout, with per-step timings and memory.
#include <CLI/CLI.hpp>

#include <algorithm>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>

#include "cli/commands.h"
#include "cli/model_args.h"
#include "cli/options.h"
#include "core/autocast.h"
#include "core/error.h"
#include "core/log.h"
#include "core/runtime.h"
#include "data/action_rows.h"
#include "data/actions.h"
#include "data/episode_clip.h"
#include "infer/stream_stats.h"
#include "infer/streaming.h"
#include "infer/world_model.h"
#include "io/video.h"

namespace dojo::cli {
namespace {

// Action chunks from JSON lines, one chunk per line, read as they arrive (stdin works live):
//   [[...], [...], [...], [...]]        4 rows: 384 values (the model's layout, used as given) or
//   {"actions": [[...], ...]}           the embodiment's width (raw commands: normalised with the
//                                       model's range, made chunk-relative, placed in its slot)
//   {"baseline": [...]}                 the raw command in force at the start frame
class ActionLines {
 public:
  ActionLines(std::istream& in, std::string name, std::optional<data::ActionChunker> chunker)
      : in_(in), name_(std::move(name)), chunker_(std::move(chunker)) {}

  // The next chunk [4, 384], or nothing at the end of the input.
  std::optional<torch::Tensor> next() {
    std::string line;
    while (std::getline(in_, line)) {
      ++line_no_;
      if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
      const auto where = name_ + " line " + std::to_string(line_no_);
      const auto j = nlohmann::json::parse(line, nullptr, /*allow_exceptions=*/false);
      DOJO_CHECK(!j.is_discarded(), where + ": not valid JSON");
      if (j.is_object() && j.contains("baseline")) {
        DOJO_CHECK(chunker_.has_value(), where + ": a baseline needs a model with an action range");
        const auto baseline =
            data::action_rows_from_json(nlohmann::json::array({j["baseline"]}), where + ": 'baseline'");
        DOJO_CHECK(baseline.size(1) == chunker_->width(),
                   where + ": 'baseline' must have " + std::to_string(chunker_->width()) + " values");
        chunker_->set_baseline(baseline[0]);
        continue;
      }
      const auto& rows = j.is_object() ? j.value("actions", nlohmann::json()) : j;
      const auto chunk = data::action_rows_from_json(rows, where);  // [4, w]
      DOJO_CHECK(chunk.size(0) == 4, where + ": expected 4 action rows");
      const int64_t width = chunk.size(1);
      if (static_cast<int>(width) == data::kUnifiedActionDim) return chunk;
      DOJO_CHECK(
          chunker_.has_value() && static_cast<int>(width) == chunker_->width(),
          where + ": rows must have 384 values" +
              (chunker_ ? " or " + std::to_string(chunker_->width()) + " (raw commands)" : std::string()));
      return chunker_->push(chunk);  // [4, 384]
    }
    return std::nullopt;
  }

 private:
  std::istream& in_;
  std::string name_;
  std::optional<data::ActionChunker> chunker_;
  int64_t line_no_ = 0;
};

struct StreamArgs {
  ModelArgs model;
  SinkArgs sink;
  std::string split = "val", episode, image, actions, out, fast_decoder, alignment, device = "cpu",
              precision = "fp32";
  int64_t frames = 48;
  int window = -1, student_steps = 0, size = 64;
  bool raw = false, no_cache = false, no_decode = false, json = false, no_cuda_graphs = false;
  uint64_t seed = 0;
};

int run_stream(StreamArgs a) {
  DOJO_CHECK(a.frames > 0 && a.frames % 4 == 0, "--frames must be a positive multiple of 4");
  if (!a.no_decode && a.out.empty() && !a.raw)
    throw UsageError("give --out FILE.mp4 or --raw (frames on stdout)");
  a.model.resolve_student(a.fast_decoder, nullptr);
  ScopedThreads matmul_bound(matmul_bound_command_threads("wm stream", parse_device(a.device).is_cuda()));
  infer::StreamingEngine::Options o;
  o.use_cache = !a.no_cache;
  o.decode = !a.no_decode;
  o.cuda_graphs = !a.no_cuda_graphs;
  o.device = parse_device(a.device);
  o.precision = parse_precision(a.precision);
  if (!a.fast_decoder.empty()) o.fast_decoder = models::load_fast_decoder(a.fast_decoder);
  if (!a.model.text_context.empty()) o.text_context = infer::load_text_context(a.model.text_context);
  auto engine = infer::StreamingEngine::load(
      a.model.checkpoint, a.model.tokenizer, o, [&](infer::StudentConfig& student) {
        if (a.window >= 0) {
          student.window_frames = a.window;
          if (a.sink.frames < 0) student.sink_frames = std::min<int64_t>(student.sink_frames, a.window);
        }
        if (a.student_steps > 0) student.steps = a.student_steps;
        if (!a.alignment.empty()) {
          student.action_alignment = infer::parse_action_alignment(a.alignment, "--action-alignment");
          // The released scripts' alignments come without a sink; one asked for as well is refused.
          if (student.action_alignment != infer::ActionAlignment::kTraining && a.sink.frames < 0)
            student.sink_frames = 0;
        }
        a.sink.apply(student);
      });
  const auto student = engine.options().student;

  // The start frame and, without --actions, the recorded actions (looped past their end). Raw
  // command lines are read in the dataset robot's units (its slot, the model's range for it or the
  // dataset's statistics), else in the units of the one slot the model records.
  torch::Tensor first, recorded;
  auto chunker = data::single_slot_chunker(engine.action_ranges(), "world model actions");
  if (!a.image.empty()) {
    first = io::resize_center_crop(io::VideoReader(a.image).read_frame(0).unsqueeze(0), a.size, a.size);
  } else {
    // With an actions file only the first frame is needed, so any episode of 13+ frames will do.
    const int chunks = a.actions.empty() ? 4 : 1;
    const data::RolloutData rollout_data(
        a.model.data, chunks, data::parse_action_ranges(engine.action_ranges(), "world model actions"),
        a.model.data_options());
    LOG_INFO("wm stream: ", rollout_data.describe());
    const auto clip = rollout_data.read(rollout_data.find(a.split, a.episode));
    first = clip.video.narrow(0, 0, 1);  // [1, H, W, 3]
    recorded = clip.actions;             // [48, 384]
    if (rollout_data.normalization() != "none") {
      chunker.emplace(data::slot_by_name(rollout_data.action_slot()), rollout_data.action_range());
      chunker->set_baseline(clip.raw_baseline);
    }
  }
  std::ifstream file;
  std::unique_ptr<ActionLines> lines;
  if (a.actions == "-") {
    lines = std::make_unique<ActionLines>(std::cin, "stdin", chunker);
  } else if (!a.actions.empty()) {
    file.open(a.actions);
    DOJO_CHECK(file.good(), a.actions + ": cannot open the actions file");
    lines = std::make_unique<ActionLines>(file, a.actions, chunker);
  }

  std::unique_ptr<io::VideoWriter> writer;
  if (!a.out.empty()) {
    io::VideoWriterOptions w;
    w.fps = 10;  // the student's rate in the release
    writer = std::make_unique<io::VideoWriter>(a.out, w);
  }
  const auto emit = [&](const torch::Tensor& frames) {  // [n, H, W, 3] uint8
    if (writer) writer->write_many(frames);
    if (a.raw) {
      const auto c = frames.contiguous();
      std::fwrite(c.data_ptr<uint8_t>(), 1, static_cast<size_t>(c.numel()), stdout);
      std::fflush(stdout);
    }
  };
  const auto frame0 = engine.reset(first, a.seed);
  if (frame0.defined()) emit(frame0[0]);

  infer::StreamStats stats;
  int64_t chunks_read = 0;
  const auto next_chunk = [&]() -> std::optional<torch::Tensor> {  // [4, 384]
    if (lines) return lines->next();
    const int64_t steps = recorded.size(0) / 4, s = chunks_read++ % steps;
    return recorded.narrow(0, 4 * s, 4);
  };
  while (stats.frames() < a.frames) {
    std::vector<torch::Tensor> chunks;  // one step's actions: 1 chunk, or the window's in teleop mode
    while (static_cast<int64_t>(chunks.size()) * 4 < engine.actions_per_step()) {
      auto next = next_chunk();
      if (!next) break;
      chunks.push_back(*next);
    }
    if (static_cast<int64_t>(chunks.size()) * 4 < engine.actions_per_step()) break;
    const auto out = engine.step(torch::cat(chunks).unsqueeze(0));  // [1, 4 n, H, W, 3] | [1, 16, n, h, w]
    if (o.decode) emit(out[0]);
    stats.add(engine.last_timings(), o.decode ? out.size(1) : 4 * out.size(2));
  }
  if (writer) writer->close();
  auto summary = stats.summary();
  summary.update(nlohmann::json{
      {"checkpoint", a.model.checkpoint},
      {"window_frames", student.window_frames},
      {"sink_frames", student.sink_frames},
      {"sink_position", infer::to_string(student.sink_position)},
      {"student_steps", student.steps},
      {"action_alignment", infer::to_string(student.action_alignment)},
      {"kv_cache", o.use_cache},
      {"decode", o.decode},
      {"decoder", o.fast_decoder ? "fast" : "wan"},
      {"fast_decoder", a.fast_decoder},
      {"kv_cache_mib", engine.cache_bytes() / 1048576.0},
  });
  if (a.json && !a.raw) {
    std::printf("%s\n", summary.dump(2).c_str());
  } else {
    std::fprintf(
        stderr,
        "streamed %lld frames: %.1f frames/s (steady %.1f), step p50 %.1f ms p95 %.1f ms "
        "(denoise %.1f, re-cache %.1f, decode %.1f), RSS %.0f MiB at frame 100, %.0f MiB at the end%s%s\n",
        static_cast<long long>(stats.frames()), summary["frames_per_second"].get<double>(),
        summary["steady_frames_per_second"].get<double>(), summary["step_ms_p50"].get<double>(),
        summary["step_ms_p95"].get<double>(), summary["denoise_ms_mean"].get<double>(),
        summary["recache_ms_mean"].get<double>(), summary["decode_ms_mean"].get<double>(),
        summary["rss_mib_at_frame_100"].get<double>(), summary["rss_mib_at_end"].get<double>(),
        a.out.empty() ? "" : " -> ", a.out.c_str());
  }
  return 0;
}

}  // namespace

void register_wm_stream(CLI::App& wm) {
  auto a = std::make_shared<StreamArgs>();
  auto* cmd = wm.add_subcommand(
      "stream", "Stream the real-time student: a start frame and actions in, 4 frames per step out");
  a->model.add_options(cmd, "the student (default: the reference set's student, else its world model)");
  add_split_option(cmd, a->split);
  cmd->add_option("--episode", a->episode,
                  "Start at this episode's first frame (default: the split's first)");
  cmd->add_option("--image", a->image, "Start at this image instead of an episode (resized to --size)");
  cmd->add_option("--size", a->size, "Frame size for --image")->capture_default_str();
  cmd->add_option(
      "--actions", a->actions,
      "JSON lines of action chunks, a file or - for stdin: 4 rows of 384 values, or of the robot's "
      "own commands (normalised and made relative here; {\"baseline\": [...]} sets the start "
      "command). Default: the episode's recorded actions, looped");
  cmd->add_option("--frames", a->frames, "Frames to generate (a multiple of 4)")->capture_default_str();
  cmd->add_option("--window", a->window, "Earlier latent frames attended (default: the student's)")
      ->check(CLI::NonNegativeNumber);
  a->sink.add_options(cmd);
  cmd->add_option("--student-steps", a->student_steps,
                  "Denoising hops per latent frame, 1-4 (default: the student's)")
      ->check(CLI::Range(1, 4));
  cmd->add_option("--action-alignment", a->alignment,
                  "training (default: a new frame uses its own 4 actions), or the released scripts' "
                  "released_offline (8-action lag) / released_teleop (12 actions per step, 8 dropped)")
      ->check(CLI::IsMember({"training", "released_offline", "released_teleop"}));
  cmd->add_option(
      "--fast-decoder", a->fast_decoder,
      "Decode with this fast streaming decoder (dojo tokenizer fast-decoder) instead of the Wan decoder "
      "(default with the reference set: its own, when it has one)");
  cmd->add_flag("--raw", a->raw, "Write raw RGB frames (H x W x 3 bytes each) to stdout");
  cmd->add_flag("--no-cache", a->no_cache,
                "Recompute the whole history every hop (the plain reference path)");
  cmd->add_flag("--no-decode", a->no_decode, "Generate latents only (times the DiT alone)");
  cmd->add_flag("--no-cuda-graphs", a->no_cuda_graphs,
                "On CUDA, dispatch the hops op by op instead of replaying them as CUDA graphs");
  add_seed_option(cmd, a->seed);
  add_out_option(cmd, a->out, "mp4 file");
  add_json_option(cmd, a->json);
  add_device_option(cmd, a->device);
  add_precision_option(cmd, a->precision);
  cmd->callback([a] { set_action([a] { return run_stream(*a); }); });
}

}  // namespace dojo::cli
