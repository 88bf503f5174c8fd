#include "recipes/step_speed.h"

#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <numeric>
#include <vector>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/gemm_census.h"
#include "core/log.h"
#include "core/runtime.h"
#include "core/safetensors.h"
#include "core/state_dict.h"
#include "diffusion/flow_matching.h"
#include "diffusion/samplers.h"
#include "models/wan_vae.h"
#include "train/train_util.h"
#include "train/wm_train.h"

namespace dojo::recipes {
namespace fs = std::filesystem;

namespace {

using Clock = std::chrono::steady_clock;

double ms_since(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

// Mean, median and fastest of a list of step times in milliseconds.
nlohmann::json summarize(std::vector<double> ms, int64_t items_per_step, const std::string& unit) {
  std::sort(ms.begin(), ms.end());
  const double mean = std::accumulate(ms.begin(), ms.end(), 0.0) / static_cast<double>(ms.size());
  return {{"steps", ms.size()},
          {"ms_mean", mean},
          {"ms_p50", ms[ms.size() / 2]},
          {"ms_min", ms.front()},
          {unit + "_per_second", 1000.0 * static_cast<double>(items_per_step) / mean}};
}

// Per-seed draws of the inputs, so Python reads them back rather than redrawing them.
struct Clips {
  torch::Tensor x0, actions;  // [B, 16, T, h, w], [B, 4 (T - 1), A]
};

Clips draw_clips(const StepSpeedOptions& o, int64_t batch, uint64_t seed) {
  auto gen = train::cpu_generator(seed);
  const int64_t T = o.latent_frames;
  Clips c;
  c.x0 = torch::randn({batch, o.model.in_channels, T, o.height / 8, o.width / 8}, gen);
  c.actions =
      torch::randn({batch, o.model.actions_per_latent_frame * (T - 1), o.model.action_dim}, gen) * 0.1;
  return c;
}

torch::Tensor frame0_mask(const torch::Tensor& x0) {
  auto mask = torch::zeros({x0.size(0), 1, x0.size(2), x0.size(3), x0.size(4)});
  mask.select(2, 0).fill_(1);
  return mask;  // [B, 1, T, h, w]
}

nlohmann::json time_sampling(models::ActionDit& net, const StepSpeedOptions& o, const fs::path& out) {
  const auto clips = draw_clips(o, o.sample_batch, o.seed + 1);
  auto gen = train::cpu_generator(o.seed + 2);
  const auto noise = torch::randn(clips.x0.sizes(), gen);    // [B, 16, T, h, w]
  const auto sigma = torch::rand({o.sample_batch, 1}, gen);  // [B, 1]
  const auto x_t = sigma.view({-1, 1, 1, 1, 1}) * noise + (1 - sigma.view({-1, 1, 1, 1, 1})) * clips.x0;
  const auto mask = frame0_mask(clips.x0);
  c10::InferenceMode inference;
  net->eval();
  models::DitInputs in;
  in.timesteps = sigma * 1000.0;
  // As the engine's sampler (infer/world_model.cpp) runs a step: the action MLPs, the context's
  // projection and the RoPE angles ran once for the chunk's 35 steps.
  in.action_embedding = net->embed_actions(clips.actions, o.latent_frames - 1);
  in.projected_context =
      net->project_context(torch::zeros({o.sample_batch, 1, o.model.crossattn_emb_channels}));
  std::tie(in.rope_cos, in.rope_sin) = net->rope_cos_sin(o.latent_frames, o.height / 16, o.width / 16, 0);
  auto velocity = [&] { return models::denoise_velocity(*net, in, x_t, clips.x0, noise, mask); };
  if (!out.empty())
    save_safetensors(out / "sample.safetensors", {{"x0", clips.x0},
                                                  {"actions", clips.actions},
                                                  {"noise", noise},
                                                  {"sigma", sigma},
                                                  {"velocity", velocity()}});
  std::vector<double> ms;
  for (int64_t i = 0; i < o.warmup + o.repeats; ++i) {
    const auto start = Clock::now();
    velocity();
    if (i >= o.warmup) ms.push_back(ms_since(start));
  }
  return summarize(ms, o.sample_batch, "clips");
}

nlohmann::json time_streaming(models::ActionDit& net, const StepSpeedOptions& o, const fs::path& out) {
  models::WanVaeConfig vae;
  vae.dim = 16;  // encodes the start frame only: its width does not enter the step
  torch::manual_seed(o.seed);
  models::WanVae tokenizer(vae);
  infer::StreamingEngine::Options eo;
  eo.student = o.student;
  eo.decode = false;
  infer::StreamingEngine engine(net, tokenizer, eo);
  auto gen = train::cpu_generator(o.seed + 3);
  const auto first = torch::randint(0, 256, {1, o.height, o.width, 3}, gen, torch::kUInt8);  // [1, H, W, 3]
  // Enough steps to fill the window and move the sink past it.
  const int64_t checked = o.student.window_frames + 3;
  const auto actions =
      torch::randn({checked, 1, o.model.actions_per_latent_frame, o.model.action_dim}, gen) * 0.1;
  const uint64_t stream_seed = o.seed + 4;
  engine.reset(first, stream_seed);
  std::vector<torch::Tensor> latents;
  for (int64_t i = 0; i < checked; ++i) latents.push_back(engine.step(actions[i]));  // [1, 16, 1, h, w]
  if (!out.empty()) {
    torch::Tensor z0;
    {
      c10::InferenceMode inference;
      z0 = tokenizer->encode_latents(models::video_to_model(first.unsqueeze(1)));  // [1, 16, 1, h, w]
    }
    save_safetensors(out / "stream.safetensors",
                     {{"z0", z0}, {"actions", actions}, {"latents", torch::stack(latents)}});
  }
  std::vector<double> ms;
  const auto step_actions = actions[0];
  for (int64_t i = 0; i < o.warmup + o.stream_steps; ++i) {
    const auto start = Clock::now();
    engine.step(step_actions);
    if (i >= o.warmup) ms.push_back(ms_since(start));
  }
  auto report = summarize(ms, 4, "frames");  // 4 video frames per latent frame
  report["stream_seed"] = stream_seed;
  report["checked_steps"] = checked;
  return report;
}

nlohmann::json time_training(models::ActionDit& net, const StepSpeedOptions& o, const fs::path& out) {
  train::WmTrainOptions to;
  net->recompute_blocks = o.checkpoint_activations;
  train::WmTrainer trainer(net, to);
  const auto clips = draw_clips(o, o.train_batch, o.seed + 5);
  const uint64_t step_seed = o.seed + 6;  // step k draws its times and noise from step_seed + k
  std::vector<double> ms;
  for (int64_t i = 0; i < o.warmup + o.repeats; ++i) {
    const auto start = Clock::now();
    const auto stats = trainer.step(clips.x0, clips.actions, train::cpu_generator(step_seed + i));
    if (i >= o.warmup) ms.push_back(ms_since(start));
    if (i == 0 && !out.empty()) {
      NamedTensors tensors = {{"x0", clips.x0},
                              {"actions", clips.actions},
                              {"loss", torch::tensor(stats.loss, torch::kFloat64)},
                              {"grad_norm", torch::tensor(stats.grad_norm, torch::kFloat64)}};
      for (const auto& [name, t] : state_dict(*trainer.net())) tensors.emplace_back("after." + name, t);
      for (const auto& [name, t] : state_dict(*trainer.ema())) tensors.emplace_back("ema." + name, t);
      save_safetensors(out / "train.safetensors", tensors);
    }
  }
  auto report = summarize(ms, o.train_batch, "clips");
  // One more step, untimed, counts the step's matrix products; timed alone they are the step's
  // roofline on this machine.
  std::vector<GemmRecord> products;
  {
    GemmCensus census;
    trainer.step(clips.x0, clips.actions, train::cpu_generator(step_seed + o.warmup + o.repeats));
    products = census.records();
  }
  const auto roofline = time_alone(products, 5);
  report["gemm"] = roofline.to_json(report["ms_p50"].get<double>() / 1e3, products, 12);
  report["step_seed"] = step_seed;
  report["options"] = to.to_json();
  report["ema_gamma"] = diffusion::power_ema_gamma(to.ema_sigma_rel);
  report["flow_grid"] = to.flow.grid;  // not among the options' JSON fields
  return report;
}

nlohmann::json student_json(const infer::StudentConfig& s) {
  auto j = s.to_json();
  j["schedule"] = nlohmann::json::array();
  for (const auto& step : s.schedule())
    j["schedule"].push_back({{"trigflow_t", step.trigflow_t},
                             {"c_in", step.c_in},
                             {"c_noise", step.c_noise},
                             {"c_skip", step.c_skip},
                             {"c_out", step.c_out}});
  return j;
}

}  // namespace

nlohmann::json run_step_speed(const StepSpeedOptions& o) {
  DOJO_CHECK(o.height % 16 == 0 && o.width % 16 == 0, "step speed: the frame size must be a multiple of 16");
  DOJO_CHECK(o.latent_frames >= 2, "step speed: a clip needs at least 2 latent frames");
  DOJO_CHECK(o.repeats >= 1 && o.stream_steps >= 1 && o.warmup >= 0, "step speed: nothing to time");
  const fs::path out = o.export_dir;
  if (!out.empty()) fs::create_directories(out);
  torch::manual_seed(o.seed);
  models::ActionDit net(o.model);
  {
    // The released init zeroes the action MLPs' last layers; random values instead, so that the
    // Python reference's check covers the action path (speed does not depend on the values).
    torch::NoGradGuard no_grad;
    auto gen = train::cpu_generator(o.seed + 7);
    for (auto* mlp : {net->action_embedder_B_D.get(), net->action_embedder_B_3D.get()}) {
      mlp->fc2->weight.copy_(torch::randn(mlp->fc2->weight.sizes(), gen) * 0.02);
      mlp->fc2->bias.copy_(torch::randn(mlp->fc2->bias.sizes(), gen) * 0.02);
    }
  }
  // Each kind of step gets its own copy of the same weights: streaming puts its network in eval
  // mode, training changes the weights.
  auto copy = [&] {
    models::ActionDit c(o.model);
    load_state_dict(*c, state_dict(*net));
    return c;
  };
  if (!out.empty()) save_safetensors(out / "weights.safetensors", state_dict(*net));

  nlohmann::json report = {{"arch", o.arch},
                           {"model", o.model.to_json()},
                           {"parameters", models::dit_parameter_count(o.model)},
                           {"size", {o.height, o.width}},
                           {"latent_frames", o.latent_frames},
                           {"train_batch", o.train_batch},
                           {"sample_batch", o.sample_batch},
                           {"student", student_json(o.student)},
                           {"seed", o.seed},
                           {"warmup", o.warmup},
                           {"machine", version_info()}};
  LOG_INFO("step speed: sampling, ", o.repeats, " steps of ", o.sample_batch, " clips");
  auto sample_net = copy();
  report["sample"] = time_sampling(sample_net, o, out);
  LOG_INFO("step speed: streaming, ", o.stream_steps, " steps");
  auto stream_net = copy();
  report["stream"] = time_streaming(stream_net, o, out);
  LOG_INFO("step speed: training, ", o.repeats, " steps of ", o.train_batch, " clips");
  auto train_net = copy();
  report["train"] = time_training(train_net, o, out);
  const double flops = models::dit_forward_flops(o.model, o.latent_frames, o.height / 8, o.width / 8);
  report["train"]["checkpoint_activations"] = o.checkpoint_activations;
  report["train"]["matmul_gflops_per_second"] =
      3 * flops * report["train"]["clips_per_second"].get<double>() / 1e9;
  if (!out.empty()) write_file_atomic(out / "config.json", report.dump(2) + "\n");
  return report;
}

}  // namespace dojo::recipes
