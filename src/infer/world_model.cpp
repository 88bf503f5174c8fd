#include "infer/world_model.h"

#include <ATen/CPUGeneratorImpl.h>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/safetensors.h"
#include "core/torch_file.h"

namespace dojo::infer {

diffusion::Solver parse_solver(const std::string& text) {
  if (text == "unipc") return diffusion::Solver::kUniPC;
  if (text == "euler") return diffusion::Solver::kEuler;
  throw Error("unknown solver '" + text + "' (expected unipc or euler)");
}

namespace {

// The sampler a world-model checkpoint's config was trained for (its "sampler" entry).
SamplerOptions sampler_from_config(const nlohmann::json& config, const std::filesystem::path& checkpoint) {
  SamplerOptions s;
  if (config.contains("sampler") && config["sampler"].contains("shift")) {
    DOJO_CHECK(config["sampler"]["shift"].is_number() && config["sampler"]["shift"].get<double>() > 0,
               checkpoint.string() + "/config.json: field 'sampler.shift' must be a positive number");
    s.shift = config["sampler"]["shift"].get<double>();
  }
  return s;
}

}  // namespace

ConcatMode parse_concat_mode(const std::string& text) {
  if (text == "aligned") return ConcatMode::kAligned;
  if (text == "released") return ConcatMode::kReleased;
  throw Error("unknown concat mode '" + text + "' (expected aligned or released)");
}

WorldModel::WorldModel(models::ActionDit net, models::WanVae tokenizer, torch::Device device,
                       Precision precision)
    : net_(std::move(net)), tokenizer_(std::move(tokenizer)), device_(device), precision_(precision) {
  check_precision_supported(precision_, device_.type());
  net_->to(device_);
  tokenizer_->to(device_);
  net_->eval();
  tokenizer_->eval();
}

WorldModel WorldModel::load(const std::filesystem::path& checkpoint, const std::filesystem::path& tokenizer,
                            torch::Device device, Precision precision) {
  check_precision_supported(precision, device.type());  // before reading any weights
  const auto config = Checkpoint::open(resolve_checkpoint_dir(checkpoint)).config();
  WorldModel model(models::load_world_model(checkpoint), models::load_tokenizer(tokenizer), device,
                   precision);
  model.trained_sampler_ = sampler_from_config(config, checkpoint);
  model.action_ranges_ = config.value("actions", nlohmann::json::object());
  return model;
}

torch::Tensor WorldModel::reconstruct_frames(const torch::Tensor& frames) {
  return reconstruct_video(frames.unsqueeze(1)).select(1, 0);  // [B, H, W, 3]
}

torch::Tensor WorldModel::reconstruct_video(const torch::Tensor& video) {
  return models::reconstruct_frames(tokenizer_, video.to(device_)).to(torch::kCPU);  // [B, 1 + 4k, H, W, 3]
}

torch::Tensor WorldModel::reconstruct_chunks(const torch::Tensor& video, ConcatMode concat) {
  DOJO_CHECK(video.dim() == 5 && (video.size(1) - 1) % kChunkActions == 0 && video.size(1) > 1,
             "reconstruct_chunks: expected [B, 1 + 12 K, H, W, 3] frames");
  const int64_t chunks = (video.size(1) - 1) / kChunkActions;
  std::vector<torch::Tensor> parts;
  for (int64_t k = 0; k < chunks; ++k) {
    const auto chunk =
        reconstruct_video(video.narrow(1, k * kChunkActions, 1 + kChunkActions));  // [B, 13, ...]
    if (k == 0)
      parts.push_back(chunk);
    else
      parts.push_back(concat == ConcatMode::kAligned ? chunk.narrow(1, 1, kChunkActions)
                                                     : chunk.narrow(1, 0, kChunkActions));
  }
  return torch::cat(parts, 1);  // [B, 1 + 12 K, H, W, 3]
}

torch::Tensor load_text_context(const std::filesystem::path& file) {
  torch::Tensor context;
  const std::string ext = file.extension().string();
  if (ext == ".pt" || ext == ".pth") {
    // A torch.save file holding the tensor itself or a dict with one tensor (the released empty-
    // prompt embedding asset), read without running anything (core/torch_file.h).
    const TorchFile torch_file = TorchFile::open(file);
    if (TorchFile::is_tensor(torch_file.root())) {
      context = torch_file.tensor(torch_file.root());
    } else {
      const auto tensors = torch_file.tensors();
      DOJO_CHECK(tensors.size() == 1, file.string() + ": holds " + std::to_string(tensors.size()) +
                                          " tensors, not one prompt embedding");
      context = tensors[0].second;
    }
  } else {
    const auto tensors = SafetensorsFile::open(file);
    DOJO_CHECK(tensors.contains("context"),
               file.string() + ": no tensor 'context' (the prompt embedding, [L, C])");
    context = tensors.tensor("context");
  }
  context = context.to(torch::kFloat32).contiguous().clone();
  if (context.dim() == 2) context = context.unsqueeze(0);
  DOJO_CHECK(context.dim() == 3 && context.size(0) == 1 && context.size(1) > 0,
             file.string() + ": the prompt embedding is " + shape_string(context.sizes()) +
                 ", not [L, C] or [1, L, C]");
  DOJO_CHECK(torch::isfinite(context).all().item<bool>(),
             file.string() + ": the prompt embedding holds NaN or infinity");
  return context;
}

void WorldModel::set_text_context(const torch::Tensor& context, const std::string& source) {
  const int64_t channels = net_->config.crossattn_emb_channels;
  DOJO_CHECK(context.dim() == 3 && context.size(0) == 1 && context.size(2) == channels,
             source + ": the text context is " + shape_string(context.sizes()) +
                 "; this model takes [1, L, " + std::to_string(channels) + "]");
  text_context_ = context.to(device_, torch::kFloat32);
}

torch::Tensor WorldModel::predict_chunk(const torch::Tensor& cond, const torch::Tensor& actions,
                                        uint64_t seed, const SamplerOptions& sampler) {
  DOJO_CHECK(cond.dim() == 4 && cond.size(3) == 3 && cond.scalar_type() == torch::kUInt8,
             "predict_chunk: conditioning frames must be [B, H, W, 3] uint8");
  DOJO_CHECK(actions.dim() == 3 && actions.size(0) == cond.size(0) && actions.size(1) == kChunkActions,
             "predict_chunk: actions must be [B, 12, action_dim] for B = " + std::to_string(cond.size(0)));
  torch::NoGradGuard no_grad;
  const int64_t batch = cond.size(0);
  // The causal tokenizer encodes frame 0 on its own, so the conditioning latent of a
  // [cond, 12 blank frames] clip is the latent of cond alone.
  const auto z_cond = tokenizer_->encode_latents(
      models::video_to_model(cond.to(device_).unsqueeze(1)));  // [B, 16, 1, h, w] float32
  const auto opts = z_cond.options();
  const int64_t latent_frames = 1 + kChunkActions / 4;
  auto gt = torch::zeros({batch, z_cond.size(1), latent_frames, z_cond.size(3), z_cond.size(4)}, opts);
  gt.narrow(2, 0, 1).copy_(z_cond);  // [B, 16, 4, h, w]
  auto mask = torch::zeros({batch, 1, latent_frames, z_cond.size(3), z_cond.size(4)}, opts);
  mask.narrow(2, 0, 1).fill_(1);
  // Drawn on the CPU and moved, so a seed gives the same noise on every device.
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  const auto noise = torch::randn(gt.sizes(), gen).to(opts);
  const auto acts = actions.to(device_, torch::kFloat);

  const bool guided = sampler.action_guidance != 1.0;
  // What every step of the chunk shares, computed once: the text context (or the zeros that stand
  // in for it) through its projection, the action MLPs' outputs (guided: for [actions; zero
  // actions]) and the tokens' RoPE angles.
  const auto all_actions = guided ? torch::cat({acts, torch::zeros_like(acts)}) : acts;  // [rows, 12, A]
  const bool per_frame = net_->config.whole_clip_actions == 0;  // else the ablation's injection, per call
  models::DitActionEmbedding embedded;
  torch::Tensor projected;
  {
    AutocastGuard autocast(device_.type(), precision_);
    if (per_frame) embedded = net_->embed_actions(all_actions, latent_frames - 1);
    projected = net_->project_context(text_context_.defined()
                                          ? text_context_  // [1, L, C]
                                          : torch::zeros({1, 1, net_->config.crossattn_emb_channels}, opts));
  }
  const int64_t p = net_->config.patch_spatial;
  const auto [rope_cos, rope_sin] = net_->rope_cos_sin(latent_frames, gt.size(3) / p, gt.size(4) / p, 0);
  const diffusion::VelocityFn velocity = [&](const torch::Tensor& x, double /*sigma*/, int64_t timestep) {
    const int64_t rows = guided ? 2 * batch : batch;
    models::DitInputs in;
    in.timesteps = torch::full({rows, 1}, static_cast<double>(timestep), opts);
    in.condition_mask = guided ? mask.repeat({2, 1, 1, 1, 1}) : mask;
    in.action_embedding = embedded;
    if (!per_frame) in.actions = all_actions;
    in.projected_context = projected.expand({rows, -1, -1});
    in.rope_cos = rope_cos;
    in.rope_sin = rope_sin;
    // Only the network runs in the lower precision; the solver's updates stay float32.
    AutocastGuard autocast(device_.type(), precision_);
    if (!guided) return models::denoise_velocity(*net_, in, x, gt, noise, mask).to(torch::kFloat32);
    // Both branches in one batch: [with actions; zero actions].
    const auto v = models::denoise_velocity(*net_, in, x.repeat({2, 1, 1, 1, 1}), gt.repeat({2, 1, 1, 1, 1}),
                                            noise.repeat({2, 1, 1, 1, 1}), in.condition_mask)
                       .to(torch::kFloat32);
    const auto v_actions = v.narrow(0, 0, batch), v_free = v.narrow(0, batch, batch);
    return v_free + sampler.action_guidance * (v_actions - v_free);
  };
  const auto schedule = diffusion::flow_sigma_schedule(sampler.steps, sampler.shift);
  auto x0 = diffusion::sample_flow(velocity, noise, schedule, sampler.solver);  // [B, 16, 4, h, w]
  // The sampler starts from pure noise at sigma = 0.999, so the conditioning latent ends ~1e-3
  // off its clean value; put it back exactly, so frame 0 is the tokenizer's round trip of cond.
  x0 = gt * mask + x0 * (1 - mask);
  return models::model_to_video(tokenizer_->decode_latents(x0)).to(torch::kCPU);  // [B, 13, H, W, 3]
}

torch::Tensor WorldModel::rollout(const torch::Tensor& first, const torch::Tensor& actions, uint64_t seed,
                                  const SamplerOptions& sampler, ConcatMode concat,
                                  const std::function<void(int64_t)>& on_chunk) {
  DOJO_CHECK(actions.dim() == 3 && actions.size(1) % kChunkActions == 0 && actions.size(1) > 0,
             "rollout: the action count must be a positive multiple of 12 (got " +
                 std::to_string(actions.dim() == 3 ? actions.size(1) : -1) + ")");
  const int64_t chunks = actions.size(1) / kChunkActions;
  std::vector<torch::Tensor> parts;
  auto cond = first;
  for (int64_t k = 0; k < chunks; ++k) {
    const auto chunk = predict_chunk(cond, actions.narrow(1, k * kChunkActions, kChunkActions),
                                     seed + static_cast<uint64_t>(k), sampler);  // [B, 13, H, W, 3]
    if (k == 0)
      parts.push_back(chunk);
    else
      parts.push_back(concat == ConcatMode::kAligned ? chunk.narrow(1, 1, kChunkActions)
                                                     : chunk.narrow(1, 0, kChunkActions));
    cond = chunk.select(1, kChunkActions).contiguous();  // the last predicted frame
    if (on_chunk) on_chunk(k);
  }
  return torch::cat(parts, 1);  // [B, 1 + 12 K, H, W, 3]
}

}  // namespace dojo::infer
