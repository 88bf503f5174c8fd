// The real-time student: a causal, few-step DiT that generates one latent frame (4 video frames)
// per step from the 4 actions of its transitions, attending to a bounded window of earlier frames
// through a KV cache, and a streaming decoder that turns each latent into pixels as it comes.
// Facts: ../shared/reference/self_forcing.md §3.3 and §4, dreamdojo.md §0 (rows 4 and 6) and §11.
//
// One step (self_forcing.md §3.3, the training rollout):
//   x ← ε                                   fresh noise for the new latent frame, kept for all hops
//   for each student time t_s:  x̂0 = D(x, t_s) reading the cache;  x ← cos t_{s+1}·x̂0 + sin t_{s+1}·ε
//   re-cache: one clean pass on x̂0 at t = 0 stores the frame's keys and values
//   decode x̂0 → 4 frames with the tokenizer's causal feature caches
// Actions follow the training alignment by default: the new latent frame uses the 4 actions of its
// own transitions, and cached frames keep the actions they were generated with. The released
// inference scripts' alignments are kept as compatibility modes (ActionAlignment).
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <deque>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/autocast.h"
#include "diffusion/samplers.h"
#include "infer/cuda_graph.h"
#include "models/dit.h"
#include "models/fast_decoder.h"
#include "models/wan_vae.h"

namespace dojo::infer {

// Which actions a new latent frame and its cached context see (dreamdojo.md §0 row 6). The two
// released inference scripts disagree with each other and with the training rollout; both are
// kept for parity with released outputs. w = window_frames, a "chunk" = 4 actions.
enum class ActionAlignment {
  kTraining,         // 4 actions per step; latent k is generated and cached with its own chunk k
  kReleasedOffline,  // 4 per step; after the first w latents, latent k is generated with chunk
                     // k - (w - 1) (an 8-action lag at w = 3) and cached with its own
  kReleasedTeleop,   // 4 w per step, w latents at the first step; afterwards every step rebuilds
                     // the cache from the last w latents, the oldest without actions and the others
                     // with the fresh chunks 0 .. w - 2, generates one latent with fresh chunk 0
                     // and discards the last fresh chunk
};
// "training" | "released_offline" | "released_teleop"; parse throws naming `where`.
const char* to_string(ActionAlignment a);
ActionAlignment parse_action_alignment(const std::string& name, const std::string& where);

// Where an attention sink's frames sit in RoPE time once the stream outgrows the window.
enum class SinkPosition {
  kWindowEdge,  // in the window's oldest slots (frame n attends to the sink at n - window): the
                // layout of a rollout that just fills the window, which the student trained on
  kAbsolute,    // at their own frame indices: ever farther from the new frame
};
const char* to_string(SinkPosition p);  // "window_edge" | "absolute"

// What makes a DiT a student: stored as the "student" entry of its checkpoint's config.json.
struct StudentConfig {
  int64_t window_frames = 3;  // earlier latent frames a new one attends to (released: 3)
  // The first sink_frames latent frames (frame 0 is the real start frame) stay in the window for
  // good, in place of its oldest frames, so a long stream keeps seeing where it started. 0: off.
  int64_t sink_frames = 0;
  SinkPosition sink_position = SinkPosition::kWindowEdge;
  int steps = 4;           // hops per latent frame, the first `steps` of the 4 student times
  bool bf16_times = true;  // the released streaming code's bf16 time rounding (self_forcing.md §3.1)
  ActionAlignment action_alignment = ActionAlignment::kTraining;
  nlohmann::json to_json() const;
  // Missing fields keep the defaults; a bad value throws dojo::Error naming `where` and the field.
  static StudentConfig from_json(const nlohmann::json& j, const std::string& where);
  std::vector<diffusion::StudentStep> schedule() const;  // the hops this config runs
};

// x̂0 of one student hop on TrigFlow-state latents: the net sees c_in·x at time c_noise (as
// timesteps 1000·c_noise with the DiT's scale 0.001), x̂0 = c_skip·x + c_out·v̂.
// base supplies everything but x and timesteps; x_trig: [B, 16, T, h, w].
torch::Tensor student_x0(models::ActionDitImpl& net, const models::DitInputs& base,
                         const torch::Tensor& x_trig, const diffusion::StudentStep& step);
// The same with per-frame times: x_rf [B, 16, T, h, w] (rectified-flow state), sigma [B, T]
// (0 = clean): x̂0 = x − σ·v̂(x, 1000·σ). Used by the warm-up regression and the re-cache pass.
torch::Tensor student_x0_rf(models::ActionDitImpl& net, const models::DitInputs& base,
                            const torch::Tensor& x_rf, const torch::Tensor& sigma);

// Wall time of one engine step, in milliseconds.
struct StreamTimings {
  double denoise_ms = 0;  // the student hops
  double recache_ms = 0;  // the clean pass that stores the new frame's keys and values
  double decode_ms = 0;   // latent -> pixels
  double total_ms = 0;
};

class StreamingEngine {
 public:
  struct Options {
    StudentConfig student;
    // false: no KV cache; every hop recomputes the whole history under the block-causal window
    // mask. The plain reference the cached path is tested against (cost grows with the horizon,
    // and the history must fit the network's RoPE table: max_frames latent frames).
    bool use_cache = true;
    bool decode = true;  // false: step() returns latents only (benchmarks of the DiT alone)
    // Decode with this small streaming decoder instead of the tokenizer's Wan decoder (faster,
    // a little blurrier; models/fast_decoder.h). Empty: the Wan decoder.
    models::FastDecoder fast_decoder{nullptr};
    torch::Device device = torch::kCPU;
    // Below fp32, every network runs under autocast (the DiT, the encoder and both decoders).
    Precision precision = Precision::kFloat32;
    // Below fp32: store the weights of every linear and convolution in the lower precision once,
    // instead of autocast casting them again at every op (2B parameters per forward on the 2B
    // network). Autocast casts those ops' inputs anyway, so the results agree to rounding and are
    // as close to fp32 (tested). The networks are changed in place (shared with other engines of
    // the same options); norm weights and buffers stay float32.
    bool cast_weights = true;
    // Run reset() and step() under c10::InferenceMode (less dispatch per op; streaming.cpp says
    // why). false: under a plain no-grad guard, for comparison.
    bool inference_mode = true;
    // On a CUDA device with a CUDA libtorch: once the window is full, replay each step's hops as
    // one CUDA graph (infer/cuda_graph.h), captured per ring slot, instead of dispatching their
    // ops one by one. The same kernels on the same memory: the latents agree bit for bit with the
    // eager path (`dojo wm speed` checks; docs/benchmarks.md). Applies with the KV cache and the
    // training or released_offline alignment. If a capture fails (e.g. out of memory) the hops
    // run eagerly for the engine's life, with a warning. The networks' weights must keep their
    // storage while the engine streams (training in place does; cast_weights of another engine at
    // another precision would not). Ignored on the CPU.
    bool cuda_graphs = true;
    // The prompt embedding [1, L, C] (load_text_context in world_model.h); undefined: zeros, as
    // every DojoSim model is trained.
    torch::Tensor text_context;
  };

  StreamingEngine(models::ActionDit student, models::WanVae tokenizer, Options options);
  // A student checkpoint (its config's "student" entry; a plain world-model checkpoint streams
  // with the defaults, e.g. to time an undistilled network) and its tokenizer. `adjust` edits the
  // recorded settings before they are checked (command-line overrides).
  static StreamingEngine load(const std::filesystem::path& checkpoint, const std::filesystem::path& tokenizer,
                              Options options, const std::function<void(StudentConfig&)>& adjust = {});

  // Replaces the student settings (window, hops, time rounding); takes effect at the next reset().
  void set_student(const StudentConfig& student);

  // Starts a stream at `first` [B, H, W, 3] uint8: encodes it as latent frame 0 and caches it.
  // Noise for every later frame comes from `seed`. Returns frame 0 as the tokenizer shows it,
  // [B, 1, H, W, 3] uint8 (undefined with decode off).
  torch::Tensor reset(const torch::Tensor& first, uint64_t seed);
  // actions [B, actions_per_step(), 384] (the unified layout, chunk-relative as in training) ->
  // the next frames [B, 4 n, H, W, 3] uint8, or with decode off the new latents [B, 16, n, h, w];
  // n = 1 except at the first step of the teleop compatibility mode (n = window).
  torch::Tensor step(const torch::Tensor& actions);
  // Actions one step() consumes: 4, or 4 · window in the teleop compatibility mode.
  int64_t actions_per_step() const;

  // A whole rollout: reset at first [B, H, W, 3], then one step per actions_per_step() actions of
  // [B, A, 384] -> [B, 1 + frames, H, W, 3] uint8. on_step(k) after step k.
  torch::Tensor rollout(const torch::Tensor& first, const torch::Tensor& actions, uint64_t seed,
                        const std::function<void(int64_t)>& on_step = {});

  const StreamTimings& last_timings() const { return timings_; }
  int64_t latent_frames() const { return frames_; }  // latent frames so far, frame 0 included
  // Whether full-window steps replay their hops from CUDA graphs: Options::cuda_graphs on a CUDA
  // device, a build with graph capture, the KV cache, an alignment they apply to, no failed capture.
  bool graphs_enabled() const;
  // Steps whose hops were replayed from a CUDA graph, since construction.
  int64_t graph_replays() const { return graph_replays_; }
  const Options& options() const { return options_; }
  models::ActionDit& net() { return net_; }
  models::WanVae& tokenizer() { return tokenizer_; }
  // The network's action normalisation {slot: statistics} (its checkpoint's "actions" entry).
  const nlohmann::json& action_ranges() const { return action_ranges_; }
  // Keys and values held by the cache (bytes over all blocks): flat once the window is full.
  int64_t cache_bytes() const;
  static constexpr int64_t kActionsPerStep = 4;

 private:
  torch::Tensor reset_stream(const torch::Tensor& first, uint64_t seed);  // reset() in inference mode
  torch::Tensor step_stream(const torch::Tensor& actions);                // step() in inference mode
  torch::Tensor decode(const torch::Tensor& x0);  // [B, 16, 1, h, w] -> [B, n, H, W, 3] uint8
  torch::Tensor denoise_cached(const torch::Tensor& noise, const torch::Tensor& actions);
  // The student hops on the cache for a new frame at RoPE index `offset` (or at the positions of
  // rope_cos/rope_sin when given): noise [B, 16, 1, h, w] -> x̂0.
  torch::Tensor run_hops(const torch::Tensor& noise, const torch::Tensor& actions, int64_t offset,
                         const torch::Tensor& rope_cos, const torch::Tensor& rope_sin);
  // run_hops replayed from a CUDA graph of this ring slot, captured on first use.
  torch::Tensor denoise_graphed(const torch::Tensor& noise, const torch::Tensor& actions);
  torch::Tensor denoise_reference(const torch::Tensor& noise, const torch::Tensor& actions);
  // One new latent frame: denoised with `generate_with`, cached with `cache_with`.
  torch::Tensor generate(const torch::Tensor& generate_with, const torch::Tensor& cache_with);
  void recache(const torch::Tensor& x0, const torch::Tensor& actions);
  // Stores one clean frame's keys and values at RoPE position `position` (actions undefined: none).
  void store_frame(const torch::Tensor& x0, const torch::Tensor& actions, int64_t position);
  // Teleop compatibility: the cache holds only the last window latents, re-stored with fresh actions.
  void rebuild_teleop_cache(const torch::Tensor& fresh);
  models::DitInputs inputs(const torch::Tensor& actions) const;
  // Keeps RoPE positions inside the network's table for any horizon (see step()).
  void rebase_positions();
  // Window-edge sink: moves the sink's keys to the window's oldest positions for the next frame.
  void move_sink();

  models::ActionDit net_;
  models::WanVae tokenizer_;
  Options options_;
  std::vector<diffusion::StudentStep> schedule_;
  std::vector<models::DitKvCache> cache_;
  std::unique_ptr<models::WanVaeStreamDecoder> decoder_;
  models::FastDecoderState fast_state_;
  torch::Tensor projected_context_;  // the zero text context through crossattn_proj, once
  torch::Generator generator_;
  std::vector<int64_t> latent_shape_;  // [B, 16, 1, h, w] of the stream
  int64_t frames_ = 0;
  int64_t position_base_ = 0;  // frame index that sits at RoPE position 0
  // Reference path: every clean latent and action chunk so far.
  std::vector<torch::Tensor> history_latents_, history_actions_;
  // Compatibility modes: the last chunks received (offline lag) and the last window latents (teleop).
  std::deque<torch::Tensor> recent_chunks_, window_latents_;
  StreamTimings timings_;
  // CUDA graphs of the hops, one per ring slot (the slot a frame's keys go to is fixed at capture),
  // sharing one memory pool, and the static buffers they read. They stay valid while the cache's
  // buffers do (a reset with the same batch and window keeps them) and are dropped otherwise.
  struct HopGraph {
    std::unique_ptr<CapturedCall> call;
    torch::Tensor x0;  // [B, 16, 1, h, w], its output, overwritten by each replay
  };
  std::map<int64_t, HopGraph> hop_graphs_;
  std::vector<const void*> graphed_cache_;         // the cache buffers' addresses the graphs were made on
  torch::Tensor graph_noise_;                      // [B, 16, 1, h, w]
  torch::Tensor graph_actions_;                    // [B, 4, 384]
  torch::Tensor graph_rope_cos_, graph_rope_sin_;  // [S, 1, head_dim], the new frame's positions
  bool graphs_failed_ = false;                     // a capture failed: eager from then on
  int64_t graph_replays_ = 0;
  nlohmann::json action_ranges_ = nlohmann::json::object();
};

}  // namespace dojo::infer
