#include "infer/streaming.h"

#include <ATen/CPUGeneratorImpl.h>

#include <algorithm>
#include <chrono>
#include <cmath>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/runtime.h"

namespace dojo::infer {

namespace {

double ms_since(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

// The weights autocast would cast at each op: those of linears and convolutions.
void cast_matmul_weights(torch::nn::Module& root, c10::ScalarType dtype) {
  for (const auto& m : root.modules(/*include_self=*/true)) {
    const bool matmul = dynamic_cast<torch::nn::LinearImpl*>(m.get()) != nullptr ||
                        dynamic_cast<torch::nn::Conv2dImpl*>(m.get()) != nullptr ||
                        dynamic_cast<torch::nn::Conv3dImpl*>(m.get()) != nullptr ||
                        dynamic_cast<models::CausalConv3dImpl*>(m.get()) != nullptr;
    if (!matmul) continue;
    for (auto& p : m->parameters(/*recurse=*/false)) p.set_data(p.data().to(dtype));
  }
}

// Runs `stream` (a reset or a step) under c10::InferenceMode and hands back a normal tensor.
// Inference mode skips autograd's and view tracking's dispatch for every op: the 2B student's
// forward is ~4200 small ops, and on a GPU their dispatch, not the arithmetic, sets the pace.
// What it creates (caches, latents) stays inside the engine; the result is cloned outside it, so
// callers may modify it or train on it.
template <typename Stream>
torch::Tensor in_inference_mode(bool enabled, Stream&& stream) {
  if (!enabled) {
    torch::NoGradGuard no_grad;
    return stream();
  }
  torch::Tensor out;
  {
    c10::InferenceMode inference;
    out = stream();
  }
  return out.defined() ? out.clone() : out;
}

}  // namespace

const char* to_string(ActionAlignment a) {
  switch (a) {
    case ActionAlignment::kTraining:
      return "training";
    case ActionAlignment::kReleasedOffline:
      return "released_offline";
    case ActionAlignment::kReleasedTeleop:
      return "released_teleop";
  }
  return "training";
}

ActionAlignment parse_action_alignment(const std::string& name, const std::string& where) {
  for (auto a :
       {ActionAlignment::kTraining, ActionAlignment::kReleasedOffline, ActionAlignment::kReleasedTeleop})
    if (name == to_string(a)) return a;
  throw Error(where + ": unknown action alignment '" + name +
              "' (expected training, released_offline or released_teleop)");
}

const char* to_string(SinkPosition p) { return p == SinkPosition::kAbsolute ? "absolute" : "window_edge"; }

nlohmann::json StudentConfig::to_json() const {
  return {{"window_frames", window_frames},
          {"sink_frames", sink_frames},
          {"sink_position", to_string(sink_position)},
          {"steps", steps},
          {"bf16_times", bf16_times},
          {"action_alignment", to_string(action_alignment)}};
}

StudentConfig StudentConfig::from_json(const nlohmann::json& j, const std::string& where) {
  StudentConfig c;
  DOJO_CHECK(j.is_object(), where + ": field 'student' must be an object");
  const auto field = [&](const char* name) { return where + ": field 'student." + name + "'"; };
  if (j.contains("window_frames")) {
    DOJO_CHECK(j["window_frames"].is_number_integer() && j["window_frames"].get<int64_t>() >= 0,
               field("window_frames") + " must be an integer >= 0");
    c.window_frames = j["window_frames"].get<int64_t>();
  }
  if (j.contains("sink_frames")) {
    DOJO_CHECK(j["sink_frames"].is_number_integer() && j["sink_frames"].get<int64_t>() >= 0,
               field("sink_frames") + " must be an integer >= 0");
    c.sink_frames = j["sink_frames"].get<int64_t>();
  }
  if (j.contains("sink_position")) {
    const auto& p = j["sink_position"];
    DOJO_CHECK(p.is_string() && (p == "window_edge" || p == "absolute"),
               field("sink_position") + " must be \"window_edge\" or \"absolute\"");
    c.sink_position = p == "absolute" ? SinkPosition::kAbsolute : SinkPosition::kWindowEdge;
  }
  if (j.contains("steps")) {
    DOJO_CHECK(j["steps"].is_number_integer() && j["steps"].get<int>() >= 1 && j["steps"].get<int>() <= 4,
               field("steps") + " must be an integer in [1, 4]");
    c.steps = j["steps"].get<int>();
  }
  if (j.contains("bf16_times")) {
    DOJO_CHECK(j["bf16_times"].is_boolean(), field("bf16_times") + " must be true or false");
    c.bf16_times = j["bf16_times"].get<bool>();
  }
  if (j.contains("action_alignment")) {
    DOJO_CHECK(j["action_alignment"].is_string(), field("action_alignment") + " must be a string");
    c.action_alignment =
        parse_action_alignment(j["action_alignment"].get<std::string>(), field("action_alignment"));
  }
  return c;
}

std::vector<diffusion::StudentStep> StudentConfig::schedule() const {
  DOJO_CHECK(steps >= 1 && steps <= 4, "student steps must be in [1, 4] (got " + std::to_string(steps) + ")");
  auto s = diffusion::student_schedule(bf16_times);
  s.resize(static_cast<size_t>(steps));
  return s;
}

torch::Tensor student_x0(models::ActionDitImpl& net, const models::DitInputs& base,
                         const torch::Tensor& x_trig, const diffusion::StudentStep& step) {
  models::DitInputs in = base;
  in.x = x_trig * step.c_in;  // the rectified-flow state at σ = c_noise
  if (!in.condition_mask.defined())
    in.condition_mask = torch::zeros_like(x_trig.narrow(1, 0, 1));  // student: none
  in.timesteps = torch::full({x_trig.size(0), 1}, 1000.0 * step.c_noise, x_trig.options());
  const auto v = net.forward(in).to(x_trig.scalar_type());  // [B, 16, T, h, w]
  return x_trig * step.c_skip + v * step.c_out;
}

torch::Tensor student_x0_rf(models::ActionDitImpl& net, const models::DitInputs& base,
                            const torch::Tensor& x_rf, const torch::Tensor& sigma) {
  models::DitInputs in = base;
  in.x = x_rf;
  in.timesteps = sigma * 1000.0;  // [B, T]
  if (!in.condition_mask.defined()) in.condition_mask = torch::zeros_like(x_rf.narrow(1, 0, 1));
  const auto v = net.forward(in).to(x_rf.scalar_type());  // [B, 16, T, h, w]
  return x_rf - sigma.view({sigma.size(0), 1, sigma.size(1), 1, 1}) * v;
}

StreamingEngine::StreamingEngine(models::ActionDit student, models::WanVae tokenizer, Options options)
    : net_(std::move(student)),
      tokenizer_(std::move(tokenizer)),
      options_(options),
      schedule_(options.student.schedule()),
      cache_(static_cast<size_t>(net_->config.num_blocks)) {
  set_student(options_.student);  // validates the window against the RoPE table
  check_precision_supported(options_.precision, options_.device.type());
  DOJO_CHECK(net_->config.whole_clip_actions == 0,
             "streaming: a whole-clip-action network (ablation) cannot generate frame by frame");
  net_->to(options_.device);
  tokenizer_->to(options_.device);
  net_->eval();
  tokenizer_->eval();
  if (options_.fast_decoder) {
    options_.fast_decoder->to(options_.device);
    options_.fast_decoder->eval();
  }
  torch::NoGradGuard no_grad;
  if (options_.precision != Precision::kFloat32 && options_.cast_weights) {
    const auto dtype = autocast_dtype(options_.precision);
    cast_matmul_weights(*net_, dtype);
    cast_matmul_weights(*tokenizer_, dtype);
    if (options_.fast_decoder) cast_matmul_weights(*options_.fast_decoder, dtype);
  }
  AutocastGuard autocast(options_.device.type(), options_.precision);
  const int64_t channels = net_->config.crossattn_emb_channels;
  torch::Tensor context = torch::zeros({1, 1, channels}, torch::TensorOptions(options_.device));
  if (options_.text_context.defined()) {
    DOJO_CHECK(options_.text_context.dim() == 3 && options_.text_context.size(0) == 1 &&
                   options_.text_context.size(2) == channels,
               "the text context is " + shape_string(options_.text_context.sizes()) +
                   "; this model takes [1, L, " + std::to_string(channels) + "]");
    context = options_.text_context.to(options_.device, torch::kFloat32);
  }
  projected_context_ = net_->project_context(context).to(torch::kFloat32);
}

StreamingEngine StreamingEngine::load(const std::filesystem::path& checkpoint,
                                      const std::filesystem::path& tokenizer, Options options,
                                      const std::function<void(StudentConfig&)>& adjust) {
  const auto dir = resolve_checkpoint_dir(checkpoint);
  const auto config = Checkpoint::open(dir).config();
  if (config.contains("student"))
    options.student = StudentConfig::from_json(config["student"], (dir / "config.json").string());
  else
    LOG_WARN(checkpoint.string(),
             " is not a distilled student: streaming it with the default student settings");
  if (adjust) adjust(options.student);
  StreamingEngine engine(models::load_world_model(checkpoint), models::load_tokenizer(tokenizer), options);
  engine.action_ranges_ = config.value("actions", nlohmann::json::object());
  return engine;
}

void StreamingEngine::set_student(const StudentConfig& student) {
  DOJO_CHECK(student.window_frames >= 0 && student.window_frames + 2 <= net_->pos_embedder->seq.size(0),
             "streaming: the window (" + std::to_string(student.window_frames) +
                 " frames) must be >= 0 and leave room in the network's RoPE table of " +
                 std::to_string(net_->pos_embedder->seq.size(0)) + " frames");
  DOJO_CHECK(student.action_alignment == ActionAlignment::kTraining || student.window_frames >= 1,
             std::string("streaming: the ") + to_string(student.action_alignment) +
                 " action alignment needs a window of at least 1 frame");
  DOJO_CHECK(student.action_alignment != ActionAlignment::kReleasedTeleop || options_.use_cache,
             "streaming: the released_teleop action alignment re-writes the KV cache and needs it on");
  DOJO_CHECK(student.sink_frames >= 0 && student.sink_frames <= student.window_frames,
             "streaming: the attention sink (" + std::to_string(student.sink_frames) +
                 " frames) must fit in the window (" + std::to_string(student.window_frames) + ")");
  DOJO_CHECK(student.sink_frames == 0 || student.action_alignment == ActionAlignment::kTraining,
             "streaming: an attention sink needs the training action alignment");
  // Without a cache every frame is recomputed under one set of positions; a sink that moves with
  // the window has a position per query frame, which only the cache can give.
  DOJO_CHECK(
      student.sink_frames == 0 || student.sink_position == SinkPosition::kAbsolute || options_.use_cache,
      "streaming: a window_edge attention sink needs the KV cache on (without it: an absolute "
      "sink, or none)");
  schedule_ = student.schedule();
  options_.student = student;
  frames_ = 0;  // the cache was built for the old window
}

int64_t StreamingEngine::cache_bytes() const {
  int64_t bytes = 0;
  for (const auto& c : cache_)
    if (c.k.defined()) bytes += (c.k.numel() + c.v.numel()) * static_cast<int64_t>(c.k.element_size());
  return bytes;
}

models::DitInputs StreamingEngine::inputs(const torch::Tensor& actions) const {
  models::DitInputs in;
  in.projected_context = projected_context_.expand({latent_shape_[0], -1, -1});
  in.actions = actions;
  return in;
}

torch::Tensor StreamingEngine::reset(const torch::Tensor& first, uint64_t seed) {
  return in_inference_mode(options_.inference_mode, [&] { return reset_stream(first, seed); });
}

torch::Tensor StreamingEngine::step(const torch::Tensor& actions) {
  return in_inference_mode(options_.inference_mode, [&] { return step_stream(actions); });
}

torch::Tensor StreamingEngine::reset_stream(const torch::Tensor& first, uint64_t seed) {
  DOJO_CHECK(first.dim() == 4 && first.size(3) == 3 && first.scalar_type() == torch::kUInt8,
             "streaming: the first frame must be [B, H, W, 3] uint8");
  generator_ = at::make_generator<at::CPUGeneratorImpl>(seed);
  const auto video = models::video_to_model(first.to(options_.device).unsqueeze(1));  // [B, 3, 1, H, W]
  torch::Tensor z0;
  {
    AutocastGuard autocast(options_.device.type(), options_.precision);
    z0 = tokenizer_->encode_latents(video).to(torch::kFloat32);  // [B, 16, 1, h, w]
  }
  latent_shape_ = z0.sizes().vec();
  const int64_t tokens =
      (z0.size(3) / net_->config.patch_spatial) * (z0.size(4) / net_->config.patch_spatial);
  for (auto& c : cache_) {
    c.set_ring(options_.student.window_frames, tokens, options_.student.sink_frames);
    c.clear();
  }
  history_latents_.clear();
  history_actions_.clear();
  recent_chunks_.clear();
  window_latents_.clear();
  frames_ = 0;
  position_base_ = 0;
  recache(z0, torch::Tensor());  // frame 0: clean, no action term
  decoder_ = std::make_unique<models::WanVaeStreamDecoder>(tokenizer_);
  fast_state_.clear();
  return options_.decode ? decode(z0) : torch::Tensor();  // [B, 1, H, W, 3]
}

void StreamingEngine::rebase_positions() {
  // Attention between RoPE'd queries and keys depends only on their position difference, so all
  // positions may move together. When the next frame would leave the network's RoPE table, the
  // cached keys are rotated back by delta frames (temporal angles only) and later frames are
  // numbered from the new base: the outputs do not change, and the horizon has no limit.
  const int64_t limit = net_->pos_embedder->seq.size(0);
  if (frames_ - position_base_ < limit) return;
  // The new frame lands at position max(window, 1): position 0 means "first frame, no actions".
  const int64_t delta = frames_ - position_base_ - std::max<int64_t>(options_.student.window_frames, 1);
  const auto [cos, sin] = models::temporal_rope_shift(*net_, -delta);
  for (auto& c : cache_) c.rotate_keys(cos, sin);
  position_base_ += delta;
}

void StreamingEngine::move_sink() {
  // Frame n = frames_ attends to frames n - w .. n - 1. Once frame 0 would leave that window the
  // sink takes the oldest positions instead. Its keys hold RoPE only, and its frames' contents do
  // not depend on where they sit in time (each attended only to the sink's own frames), so
  // rotating the keys as stored (at positions 0 ..) equals re-storing them there (tested).
  // An absolute sink stays at frame 0, but is placed the same way after a rebase (rotate_keys
  // moved it with everything else) so that no position is ever rotated more than once.
  const auto& s = options_.student;
  if (s.sink_frames == 0) return;
  const int64_t target = s.sink_position == SinkPosition::kWindowEdge
                             ? std::max<int64_t>(0, frames_ - s.window_frames)
                             : 0;                  // frame index whose position the sink takes
  if (target == 0 && position_base_ == 0) return;  // where it was stored
  const auto [cos, sin] = models::temporal_rope_shift(*net_, target - position_base_);
  for (auto& c : cache_) c.place_sink(cos, sin);
}

torch::Tensor StreamingEngine::decode(const torch::Tensor& x0) {
  AutocastGuard autocast(options_.device.type(), options_.precision);
  const auto pixels = options_.fast_decoder ? options_.fast_decoder->step(x0.select(2, 0), fast_state_)
                                            : decoder_->push(tokenizer_->denormalize(x0));  // [B, 3, n, H, W]
  return models::model_to_video(pixels.to(torch::kFloat32).clamp(-1, 1)).to(torch::kCPU);   // [B, n, H, W, 3]
}

void StreamingEngine::store_frame(const torch::Tensor& x0, const torch::Tensor& actions, int64_t position) {
  AutocastGuard autocast(options_.device.type(), options_.precision);
  auto in = inputs(actions);
  in.x = x0;
  in.condition_mask = torch::zeros_like(x0.narrow(1, 0, 1));
  in.timesteps = torch::zeros({x0.size(0), 1}, x0.options());
  in.frame_offset = position;
  in.kv_cache = &cache_;
  in.store_kv = true;
  net_->forward(in);  // only the stored keys and values matter
}

void StreamingEngine::recache(const torch::Tensor& x0, const torch::Tensor& actions) {
  if (options_.use_cache) {
    store_frame(x0, actions, frames_ - position_base_);
  } else {
    history_latents_.push_back(x0);
    if (actions.defined()) history_actions_.push_back(actions);
  }
  if (options_.student.action_alignment == ActionAlignment::kReleasedTeleop) {
    window_latents_.push_back(x0);
    while (static_cast<int64_t>(window_latents_.size()) > options_.student.window_frames)
      window_latents_.pop_front();
  }
  ++frames_;
}

void StreamingEngine::rebuild_teleop_cache(const torch::Tensor& fresh) {
  // As the released teleop script does every step after the first: the context is the last w
  // latents, the oldest stored as a first frame (no actions, position 0) and latent i >= 1 with
  // fresh chunk i - 1; the new frame then sits at position w.
  for (auto& c : cache_) c.clear();
  const int64_t w = static_cast<int64_t>(window_latents_.size());
  for (int64_t i = 0; i < w; ++i) {
    const auto acts = i == 0 ? torch::Tensor() : fresh.narrow(1, (i - 1) * kActionsPerStep, kActionsPerStep);
    store_frame(window_latents_[static_cast<size_t>(i)], acts, i);
  }
  position_base_ = frames_ - w;
}

torch::Tensor StreamingEngine::denoise_cached(const torch::Tensor& noise, const torch::Tensor& actions) {
  if (graphs_enabled() && cache_.front().ring_full()) {  // before: each step attends more keys
    try {
      return denoise_graphed(noise, actions);
    } catch (const Error& e) {
      LOG_WARN("streaming: ", e.what(), "; the hops run eagerly from now on");
      graphs_failed_ = true;
      hop_graphs_.clear();
    }
  }
  return run_hops(noise, actions, frames_ - position_base_, torch::Tensor(), torch::Tensor());
}

torch::Tensor StreamingEngine::run_hops(const torch::Tensor& noise, const torch::Tensor& actions,
                                        int64_t offset, const torch::Tensor& rope_cos,
                                        const torch::Tensor& rope_sin) {
  auto base = inputs(actions);
  base.frame_offset = offset;  // RoPE index of the new frame
  base.rope_cos = rope_cos;
  base.rope_sin = rope_sin;
  if (!rope_cos.defined()) {  // the hops share their positions too: their angles once, not once a hop
    const int64_t p = net_->config.patch_spatial;
    std::tie(base.rope_cos, base.rope_sin) =
        net_->rope_cos_sin(1, latent_shape_[3] / p, latent_shape_[4] / p, offset);
  }
  base.kv_cache = &cache_;
  base.store_kv = false;  // hops read the cache; the clean pass writes it
  if (actions.defined() && offset > 0) {
    // The hops share their actions: the action MLPs run once, not once a hop.
    AutocastGuard autocast(options_.device.type(), options_.precision);
    base.action_embedding = net_->embed_actions(actions, 1);
  }
  auto x = noise;  // TrigFlow state at t = π/2
  torch::Tensor x0;
  for (size_t s = 0; s < schedule_.size(); ++s) {
    {
      AutocastGuard autocast(options_.device.type(), options_.precision);
      x0 = student_x0(*net_, base, x, schedule_[s]).to(torch::kFloat32);  // [B, 16, 1, h, w]
    }
    if (s + 1 < schedule_.size()) {
      const double t = schedule_[s + 1].trigflow_t;
      x = x0 * std::cos(t) + noise * std::sin(t);  // the same noise at every hop, as released
    }
  }
  return x0;
}

bool StreamingEngine::graphs_enabled() const {
  // The teleop compatibility mode re-stores its whole window every step; it stays eager.
  return options_.cuda_graphs && options_.device.is_cuda() && options_.use_cache && !graphs_failed_ &&
         CapturedCall::available() && options_.student.action_alignment != ActionAlignment::kReleasedTeleop;
}

torch::Tensor StreamingEngine::denoise_graphed(const torch::Tensor& noise, const torch::Tensor& actions) {
  // A graph holds the addresses of the cache buffers and of its input buffers: made again when
  // either changed (a new batch size, window or precision reallocates them).
  std::vector<const void*> cache_buffers;
  for (const auto& c : cache_) {
    cache_buffers.push_back(c.k.data_ptr());
    cache_buffers.push_back(c.v.data_ptr());
  }
  if (cache_buffers != graphed_cache_ || !graph_noise_.defined() || graph_noise_.sizes() != noise.sizes() ||
      graph_actions_.sizes() != actions.sizes()) {
    hop_graphs_.clear();
    graph_noise_ = graph_actions_ = graph_rope_cos_ = graph_rope_sin_ = torch::Tensor();
    graphed_cache_ = cache_buffers;
  }
  // What changes from step to step reaches the graph through buffers: the noise, the actions and
  // the new frame's RoPE angles (its position grows until the next rebase). Which slot its keys
  // go to is decided on the host, so each slot has its own graph.
  const int64_t offset = frames_ - position_base_;
  DOJO_CHECK(offset > 0, "streaming: a graphed frame cannot be frame 0 (it has no actions)");
  const int64_t p = net_->config.patch_spatial;
  const auto [cos, sin] =
      net_->rope_cos_sin(1, latent_shape_[3] / p, latent_shape_[4] / p, offset);  // [S, 1, d]
  if (!graph_noise_.defined()) {
    graph_noise_ = torch::empty_like(noise);
    graph_actions_ = torch::empty_like(actions);
    graph_rope_cos_ = torch::empty_like(cos);
    graph_rope_sin_ = torch::empty_like(sin);
  }
  graph_noise_.copy_(noise);
  graph_actions_.copy_(actions);
  graph_rope_cos_.copy_(cos);
  graph_rope_sin_.copy_(sin);
  auto& graph = hop_graphs_[cache_.front().ring_slot()];
  if (!graph.call) {
    // Every slot's graph draws its temporaries from the first one's pool: they replay one at a
    // time and their outputs stay referenced (HopGraph::x0).
    const CapturedCall* pool = nullptr;
    for (const auto& [slot, other] : hop_graphs_)
      if (other.call) pool = other.call.get();
    const int device = options_.device.has_index() ? options_.device.index() : -1;
    // offset only decides here that the frame is not frame 0 (checked above) and range checks.
    graph.call = std::make_unique<CapturedCall>(
        [&] { graph.x0 = run_hops(graph_noise_, graph_actions_, offset, graph_rope_cos_, graph_rope_sin_); },
        device, pool);
  }
  graph.call->replay();
  ++graph_replays_;
  return graph.x0.clone();  // [B, 16, 1, h, w]; the next replay overwrites graph.x0
}

torch::Tensor StreamingEngine::denoise_reference(const torch::Tensor& noise, const torch::Tensor& actions) {
  // The whole history, clean, then the new frame; frame i attends to frames i - window ... i.
  const int64_t T = frames_ + 1, B = noise.size(0);
  const auto context = torch::cat(history_latents_, 2);  // [B, 16, T - 1, h, w]
  auto all_actions = history_actions_;
  all_actions.push_back(actions);
  const int64_t tokens =
      (noise.size(3) / net_->config.patch_spatial) * (noise.size(4) / net_->config.patch_spatial);
  auto base = inputs(torch::cat(all_actions, 1));  // [B, 4 (T - 1), 384]
  base.self_attn_mask = models::dit_block_causal_mask(T, tokens, 0, options_.student.window_frames + 1,
                                                      options_.student.sink_frames);
  auto x = noise;
  torch::Tensor x0;
  for (size_t s = 0; s < schedule_.size(); ++s) {
    const auto& step = schedule_[s];
    // Per-frame TrigFlow-equivalent inputs: clean frames at σ = 0 (c_in = 1), the new one at c_noise.
    auto sigma = torch::zeros({B, T}, noise.options());
    sigma.select(1, T - 1).fill_(step.c_noise);
    {
      AutocastGuard autocast(options_.device.type(), options_.precision);
      const auto x_rf = torch::cat({context, x * step.c_in}, 2);  // [B, 16, T, h, w]
      auto in = base;
      in.x = x_rf;
      in.condition_mask = torch::zeros_like(x_rf.narrow(1, 0, 1));
      in.timesteps = sigma * 1000.0;
      const auto v = net_->forward(in).to(torch::kFloat32).narrow(2, T - 1, 1);  // [B, 16, 1, h, w]
      x0 = x * step.c_skip + v * step.c_out;
    }
    if (s + 1 < schedule_.size()) {
      const double t = schedule_[s + 1].trigflow_t;
      x = x0 * std::cos(t) + noise * std::sin(t);
    }
  }
  return x0;
}

int64_t StreamingEngine::actions_per_step() const {
  return options_.student.action_alignment == ActionAlignment::kReleasedTeleop
             ? kActionsPerStep * options_.student.window_frames
             : kActionsPerStep;
}

torch::Tensor StreamingEngine::generate(const torch::Tensor& generate_with, const torch::Tensor& cache_with) {
  const auto start = std::chrono::steady_clock::now();
  const auto noise = torch::randn(latent_shape_, generator_).to(options_.device);  // ε [B, 16, 1, h, w]
  if (options_.use_cache) {
    rebase_positions();
    move_sink();
  }
  const auto x0 =
      options_.use_cache ? denoise_cached(noise, generate_with) : denoise_reference(noise, generate_with);
  synchronize(options_.device);  // the stage timings cover the device's work, not only its queueing
  timings_.denoise_ms += ms_since(start);
  const auto recache_start = std::chrono::steady_clock::now();
  recache(x0, cache_with);
  synchronize(options_.device);
  timings_.recache_ms += ms_since(recache_start);
  return x0;  // [B, 16, 1, h, w]
}

torch::Tensor StreamingEngine::step_stream(const torch::Tensor& actions) {
  DOJO_CHECK(frames_ > 0, "streaming: reset() must come before step()");
  const int64_t expected = actions_per_step();
  DOJO_CHECK(actions.dim() == 3 && actions.size(1) == expected && actions.size(2) == net_->config.action_dim,
             "streaming: actions must be [B, " + std::to_string(expected) + ", " +
                 std::to_string(net_->config.action_dim) + "] (" +
                 to_string(options_.student.action_alignment) + " alignment)");
  const auto start = std::chrono::steady_clock::now();
  const auto acts = actions.to(options_.device, torch::kFloat32);
  DOJO_CHECK(acts.size(0) == latent_shape_[0], "streaming: actions for batch " +
                                                   std::to_string(acts.size(0)) + ", the stream has " +
                                                   std::to_string(latent_shape_[0]));
  timings_ = StreamTimings{};
  const int64_t window = options_.student.window_frames;
  std::vector<torch::Tensor> latents;
  switch (options_.student.action_alignment) {
    case ActionAlignment::kTraining:
      latents.push_back(generate(acts, acts));
      break;
    case ActionAlignment::kReleasedOffline: {
      // The released offline script generates the first w latents in one call with their own
      // chunks; afterwards its 12-action window slides by one chunk while the new latent reads the
      // window's first chunk: chunk k - (w - 1). Re-caching uses the latent's own chunk.
      recent_chunks_.push_back(acts);
      while (static_cast<int64_t>(recent_chunks_.size()) > window) recent_chunks_.pop_front();
      const bool lagged = frames_ > window;  // frames_ is the new latent's index
      latents.push_back(generate(lagged ? recent_chunks_.front() : acts, acts));
      break;
    }
    case ActionAlignment::kReleasedTeleop:
      if (frames_ == 1) {
        // First step: w latents from the w fresh chunks, each with its own (start index 1).
        for (int64_t i = 0; i < window; ++i) {
          const auto chunk = acts.narrow(1, i * kActionsPerStep, kActionsPerStep);
          latents.push_back(generate(chunk, chunk));
        }
      } else {
        const auto rebuild_start = std::chrono::steady_clock::now();
        rebuild_teleop_cache(acts);
        timings_.recache_ms += ms_since(rebuild_start);
        const auto first_chunk = acts.narrow(1, 0, kActionsPerStep);
        latents.push_back(generate(first_chunk, first_chunk));  // fresh chunks 1 .. w - 1 unused
      }
      break;
  }

  const auto decode_start = std::chrono::steady_clock::now();
  torch::Tensor out;
  if (options_.decode) {
    std::vector<torch::Tensor> frames;
    for (const auto& x0 : latents) frames.push_back(decode(x0));  // [B, 4, H, W, 3] each
    out = torch::cat(frames, 1);
  } else {
    out = torch::cat(latents, 2);  // [B, 16, n, h, w]
  }
  synchronize(options_.device);
  timings_.decode_ms = ms_since(decode_start);
  timings_.total_ms = ms_since(start);
  return out;
}

torch::Tensor StreamingEngine::rollout(const torch::Tensor& first, const torch::Tensor& actions,
                                       uint64_t seed, const std::function<void(int64_t)>& on_step) {
  DOJO_CHECK(options_.decode, "streaming: rollout() needs decoding on");
  const int64_t per_step = actions_per_step();
  DOJO_CHECK(actions.dim() == 3 && actions.size(1) % per_step == 0 && actions.size(1) > 0,
             "streaming: the action count must be a positive multiple of " + std::to_string(per_step));
  std::vector<torch::Tensor> frames = {reset(first, seed)};  // [B, 1, H, W, 3]
  for (int64_t k = 0; k < actions.size(1) / per_step; ++k) {
    frames.push_back(step(actions.narrow(1, k * per_step, per_step)));  // [B, 4 n, H, W, 3]
    if (on_step) on_step(k);
  }
  return torch::cat(frames, 1);  // [B, 1 + frames, H, W, 3]
}

}  // namespace dojo::infer
