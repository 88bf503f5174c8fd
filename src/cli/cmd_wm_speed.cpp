// `dojo wm speed`: how fast the streaming student runs, for any architecture and frame size, on
// random weights (speed does not depend on them) or a checkpoint: frames/s, step latency, the
// stages and memory, once per decoder (none = the DiT alone, fast, wan), side by side in one run.
// This is how the GPU rows of docs/benchmarks.md are made (the 2B network at 480x640 needs no
// trained weights), and it builds in the engine-only configuration (DOJO_ENGINE_ONLY).
#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "cli/commands.h"
#include "cli/model_args.h"
#include "cli/options.h"
#include "core/autocast.h"
#include "core/error.h"
#include "core/log.h"
#include "core/runtime.h"
#include "infer/stream_stats.h"
#include "infer/streaming.h"

namespace dojo::cli {
namespace {

struct SpeedArgs {
  std::string arch = "student_2b", checkpoint, tokenizer, fast_decoder, size = "480x640";
  std::vector<std::string> decoders = {"none", "fast", "wan"};
  int64_t vae_dim = 96;  // Wan2.1's base width
  int64_t steps = 50, warmup = -1, window = -1;
  SinkArgs sink;
  int student_steps = 0;
  std::string device = "cpu", precision = "fp32";
  uint64_t seed = 0;
  bool json = false, fp32_weights = false, no_inference_mode = false, no_cuda_graphs = false;
};

// The networks of one run, built once and shared by the engines of every decoder row.
struct Networks {
  models::ActionDit net{nullptr};
  models::WanVae tokenizer{nullptr};
  models::FastDecoder fast_decoder{nullptr};
  infer::StudentConfig student;
  std::string description;
};

Networks build_networks(const SpeedArgs& a) {
  Networks n;
  if (!a.checkpoint.empty()) {
    DOJO_CHECK(!a.tokenizer.empty(), "--checkpoint needs --tokenizer (the tokenizer it was trained with)");
    // load() reads the student settings recorded with the checkpoint.
    auto engine = infer::StreamingEngine::load(a.checkpoint, a.tokenizer, {});
    n.net = engine.net();
    n.tokenizer = engine.tokenizer();
    n.student = engine.options().student;
    n.description = a.checkpoint;
  } else {
    torch::manual_seed(a.seed);
    n.net = models::ActionDit(dit_architecture(a.arch, "--arch"));
    models::WanVaeConfig vae;
    vae.dim = a.vae_dim;
    n.tokenizer = models::WanVae(vae);
    n.description = a.arch + " (random weights), Wan VAE dim " + std::to_string(a.vae_dim);
  }
  n.fast_decoder = a.fast_decoder.empty() ? models::FastDecoder(models::FastDecoderConfig{})
                                          : models::load_fast_decoder(a.fast_decoder);
  if (a.window >= 0) {
    n.student.window_frames = a.window;
    if (a.sink.frames < 0) n.student.sink_frames = std::min(n.student.sink_frames, a.window);
  }
  a.sink.apply(n.student);
  if (a.student_steps > 0) n.student.steps = a.student_steps;
  return n;
}

// One decoder row: warm-up steps, then `steps` timed ones.
nlohmann::json time_decoder(const Networks& n, const std::string& decoder, const SpeedArgs& a,
                            torch::Device device, Precision precision, int64_t height, int64_t width) {
  infer::StreamingEngine::Options o;
  o.student = n.student;
  o.device = device;
  o.precision = precision;
  o.decode = decoder != "none";
  o.cast_weights = !a.fp32_weights;
  o.inference_mode = !a.no_inference_mode;
  o.cuda_graphs = !a.no_cuda_graphs;
  if (decoder == "fast") o.fast_decoder = n.fast_decoder;
  infer::StreamingEngine engine(n.net, n.tokenizer, o);
  torch::manual_seed(a.seed);
  const auto first = torch::randint(0, 256, {1, height, width, 3}, torch::kUInt8);  // [1, H, W, 3]
  const auto actions = torch::randn({1, 4, n.net->config.action_dim}) * 0.1;        // [1, 4, 384]
  engine.reset(first, a.seed);
  // Until the window is full the cache grows each step (new allocations, longer attention); with
  // CUDA graphs, the window + 1 steps after it capture a graph per ring slot.
  const bool graphs = engine.graphs_enabled();
  const int64_t warmup =
      a.warmup >= 0 ? a.warmup : n.student.window_frames + 3 + (graphs ? n.student.window_frames + 1 : 0);
  for (int64_t i = 0; i < warmup; ++i) engine.step(actions);
  infer::StreamStats stats;
  for (int64_t i = 0; i < a.steps; ++i) {
    const auto out = engine.step(actions);  // [1, 4, H, W, 3] | [1, 16, 1, h, w]
    stats.add(engine.last_timings(), o.decode ? out.size(1) : 4 * out.size(2));
  }
  auto row = stats.summary();
  row["decoder"] = decoder;
  row["kv_cache_mib"] = engine.cache_bytes() / 1048576.0;
  row["cuda_graph_replays"] = engine.graph_replays();
  return row;
}

// The latents of the same stream with the hops replayed from CUDA graphs and dispatched eagerly:
// the largest absolute difference over 2 windows + 3 steps, each with fresh actions: the ring is
// full after a window, and the window + 1 steps after that capture every slot's graph and replay
// one again. Empty when graphs do not apply (the CPU, a build without them, the teleop alignment).
std::optional<double> graphs_against_eager(const Networks& n, const SpeedArgs& a, torch::Device device,
                                           Precision precision, int64_t height, int64_t width) {
  const int64_t steps = 2 * n.student.window_frames + 3;
  torch::manual_seed(a.seed);
  const auto first = torch::randint(0, 256, {1, height, width, 3}, torch::kUInt8);   // [1, H, W, 3]
  const auto actions = torch::randn({steps, 1, 4, n.net->config.action_dim}) * 0.1;  // per step [1, 4, 384]
  std::vector<torch::Tensor> latents[2];
  for (int graphs = 1; graphs >= 0; --graphs) {  // graphed first: it says whether they apply
    infer::StreamingEngine::Options o;
    o.student = n.student;
    o.device = device;
    o.precision = precision;
    o.decode = false;
    o.cast_weights = !a.fp32_weights;
    o.inference_mode = !a.no_inference_mode;
    o.cuda_graphs = graphs == 1;
    infer::StreamingEngine engine(n.net, n.tokenizer, o);
    if (graphs == 1 && !engine.graphs_enabled()) return std::nullopt;
    engine.reset(first, a.seed);
    for (int64_t i = 0; i < steps; ++i) latents[graphs].push_back(engine.step(actions[i]).to(torch::kCPU));
    DOJO_CHECK(graphs == 0 || engine.graph_replays() > 0,
               "wm speed: no step replayed a CUDA graph (capture failed: see the warning above)");
  }
  double worst = 0;
  for (int64_t i = 0; i < steps; ++i)
    worst = std::max(worst, (latents[0][i] - latents[1][i]).abs().max().item<double>());
  return worst;
}

int run_speed(const SpeedArgs& a) {
  DOJO_CHECK(a.steps >= 3, "--steps must be at least 3");
  for (const auto& d : a.decoders)
    if (d != "none" && d != "fast" && d != "wan")
      throw UsageError("--decoders: unknown decoder '" + d + "' (none, fast or wan)");
  const auto device = parse_device(a.device);
  const auto precision = parse_precision(a.precision);
  check_precision_supported(precision, device.type());
  const auto [height, width] = parse_size(a.size);
  ScopedThreads matmul_bound(matmul_bound_command_threads("wm speed", device.is_cuda()));
  torch::NoGradGuard no_grad;

  const auto networks = build_networks(a);
  const auto& s = networks.student;
  nlohmann::json report = {
      {"model", networks.description},
      {"parameters", models::dit_parameter_count(networks.net->config)},
      {"size", a.size},
      {"device", device.str()},
      {"precision", to_string(precision)},
      {"inference_mode", !a.no_inference_mode},
      {"weights", precision == Precision::kFloat32 || a.fp32_weights ? "fp32" : to_string(precision)},
      {"window_frames", s.window_frames},
      {"sink_frames", s.sink_frames},
      {"sink_position", infer::to_string(s.sink_position)},
      {"student_steps", s.steps},
      {"timed_steps", a.steps},
      {"torch", torch_version()},
      {"rows", nlohmann::json::array()}};
  std::optional<double> diff;
  if (!a.no_cuda_graphs) diff = graphs_against_eager(networks, a, device, precision, height, width);
  const bool graphs = diff.has_value();
  report["cuda_graphs"] = graphs;
  if (graphs) {
    LOG_INFO("wm speed: CUDA graphs against eager dispatch, largest latent difference ", *diff);
    report["cuda_graphs_max_abs_diff"] = *diff;
  }
  for (const auto& decoder : a.decoders) {
    LOG_INFO("wm speed: decoder ", decoder, ", ", a.steps, " timed steps");
    report["rows"].push_back(time_decoder(networks, decoder, a, device, precision, height, width));
  }
  if (a.json) {
    std::printf("%s\n", report.dump(2).c_str());
    return 0;
  }
  std::printf("%s, %lld parameters, %s on %s (%s), window %lld + sink %lld, %d hops, torch %s\n\n",
              networks.description.c_str(), static_cast<long long>(report["parameters"].get<int64_t>()),
              a.size.c_str(), device.str().c_str(), to_string(precision).c_str(),
              static_cast<long long>(s.window_frames), static_cast<long long>(s.sink_frames), s.steps,
              torch_version().c_str());
  if (graphs)
    std::printf("Hops replayed as CUDA graphs; largest latent difference against eager dispatch: %.3g\n\n",
                report["cuda_graphs_max_abs_diff"].get<double>());
  std::printf(
      "| decoder | frames/s | step p50 ms | step p95 ms | denoise ms | re-cache ms | decode ms | "
      "KV cache MiB | RSS MiB (frame 100 / end) |\n|---|---|---|---|---|---|---|---|---|\n");
  for (const auto& r : report["rows"])
    std::printf("| %s | %.1f | %.1f | %.1f | %.1f | %.1f | %.1f | %.1f | %.0f / %.0f |\n",
                r["decoder"].get<std::string>().c_str(), r["steady_frames_per_second"].get<double>(),
                r["step_ms_p50"].get<double>(), r["step_ms_p95"].get<double>(),
                r["denoise_ms_mean"].get<double>(), r["recache_ms_mean"].get<double>(),
                r["decode_ms_mean"].get<double>(), r["kv_cache_mib"].get<double>(),
                r["rss_mib_at_frame_100"].get<double>(), r["rss_mib_at_end"].get<double>());
  return 0;
}

}  // namespace

void register_wm_speed(CLI::App& wm) {
  auto a = std::make_shared<SpeedArgs>();
  auto* cmd = wm.add_subcommand(
      "speed",
      "Time the streaming student (random weights of an architecture, or a checkpoint) per decoder: "
      "frames/s, step latency, stages, memory");
  cmd->add_option("--arch", a->arch,
                  "Random-weight network: student_2b | 2b (released_2b) | 14b | small | tiny")
      ->capture_default_str();
  cmd->add_option("--checkpoint", a->checkpoint, "Time this student checkpoint instead (needs --tokenizer)");
  cmd->add_option("--tokenizer", a->tokenizer, "The checkpoint's tokenizer");
  cmd->add_option("--fast-decoder", a->fast_decoder, "A trained fast decoder (default: random weights)");
  cmd->add_option("--vae-dim", a->vae_dim, "Base width of the random Wan VAE (Wan2.1: 96)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--size", a->size, "Frame size HxW")->capture_default_str();
  cmd->add_option("--decoders", a->decoders, "Rows to time: none (the DiT alone) | fast | wan")
      ->capture_default_str();
  cmd->add_option("--steps", a->steps, "Timed steps per row (4 frames each)")->capture_default_str();
  cmd->add_option("--warmup", a->warmup,
                  "Untimed steps first (default: the window + 3, so the cache is full; with CUDA graphs "
                  "a window + 1 more, so every graph is captured)");
  cmd->add_option("--window", a->window, "Window in latent frames (default: the checkpoint's, else 3)");
  a->sink.add_options(cmd);
  cmd->add_option("--student-steps", a->student_steps, "Hops per latent frame, 1-4 (default: 4)");
  cmd->add_flag("--fp32-weights", a->fp32_weights,
                "Below fp32, keep float32 weights for autocast to cast at every op (the slower path)");
  cmd->add_flag("--no-inference-mode", a->no_inference_mode,
                "Stream under a plain no-grad guard instead of inference mode (for comparison)");
  cmd->add_flag("--no-cuda-graphs", a->no_cuda_graphs,
                "On CUDA, dispatch the hops op by op instead of replaying them as CUDA graphs (with graphs, "
                "the run first checks their latents against eager dispatch and reports the largest "
                "difference)");
  add_seed_option(cmd, a->seed);
  add_json_option(cmd, a->json);
  add_device_option(cmd, a->device);
  add_precision_option(cmd, a->precision);
  cmd->callback([a] { set_action([a] { return run_speed(*a); }); });
}

}  // namespace dojo::cli
