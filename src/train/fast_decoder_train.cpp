#include "train/fast_decoder_train.h"

#include <ATen/CPUGeneratorImpl.h>
#include <torch/torch.h>

#include <cmath>

#include "core/atomic_file.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/progress.h"
#include "core/state_dict.h"
#include "models/wan_vae.h"
#include "train/data_parallel.h"
#include "train/train_loop.h"
#include "train/train_util.h"

namespace fs = std::filesystem;

namespace dojo::train {

namespace {

// PSNR in dB of frames in [-1, 1] (peak-to-peak 2), over the whole tensor.
double psnr(const torch::Tensor& a, const torch::Tensor& b) {
  const double mse = (a.clamp(-1, 1) - b.clamp(-1, 1)).pow(2).mean().item<double>();
  return 10 * std::log10(4.0 / std::max(mse, 1e-12));
}

}  // namespace

FastDecoderResult run_fast_decoder_training(const FastDecoderJob& job) {
  DOJO_CHECK(!job.data.empty(), "fast decoder: no dataset given");
  DOJO_CHECK(job.batch_size > 0, "fast decoder: the batch size must be positive");
  fs::create_directories(job.out);
  const auto ckpt_dir = job.out / "checkpoint";
  std::vector<LatentClips> sets;
  // Rank 0 encodes the latent caches; the other ranks read them once they are written.
  data_parallel().main_first("the latent caches", [&] {
    for (size_t i = 0; i < job.data.size(); ++i)
      sets.push_back(load_or_build_latent_clips(job.data[i],
                                                job.out / ("latents-" + std::to_string(i) + ".safetensors")));
  });
  const auto clips = concat_latent_clips(sets);  // latents [N, 16, 4, h, w]
  const int64_t n = clips.size(), heldout = std::max<int64_t>(1, n / 10), train_n = n - heldout;
  DOJO_CHECK(train_n > 0, "fast decoder: need at least 2 clips");

  // The teacher's frames, once: Wan decoding of every clip's latents, kept as uint8.
  auto wan = models::load_tokenizer(job.data.front().tokenizer);
  std::vector<torch::Tensor> targets;
  {
    torch::NoGradGuard no_grad;
    Progress progress("wan decoding", n, "clips");
    for (int64_t b = 0; b < n; b += 8) {
      const int64_t m = std::min<int64_t>(8, n - b);
      const auto frames = wan->decode_latents(clips.latents.narrow(0, b, m));  // [m, 3, 13, H, W]
      targets.push_back(((frames + 1) * 127.5).round().clamp(0, 255).to(torch::kUInt8));
      progress.advance(m);
    }
  }
  const auto target_u8 = torch::cat(targets);  // [N, 3, 13, H, W]
  const auto target = [&](const torch::Tensor& idx) {
    return target_u8.index_select(0, idx).to(torch::kFloat32) / 127.5 - 1;
  };

  const bool resuming = checkpoint_exists(ckpt_dir);
  torch::manual_seed(job.seed);
  models::FastDecoder decoder(
      resuming ? models::FastDecoderConfig::from_json(
                     Checkpoint::open(resolve_checkpoint_dir(ckpt_dir)).config().at("config"))
               : job.model);
  const auto heldout_idx = torch::arange(train_n, n);
  const auto heldout_psnr = [&] {
    torch::NoGradGuard no_grad;
    decoder->eval();
    const auto device = decoder->parameters().front().device();  // the job's while it trains
    AutocastGuard fp32(device.type(), Precision::kFloat32);      // the same measure in every precision
    const double p =
        psnr(decoder->decode(clips.latents.index_select(0, heldout_idx).to(device)).to(torch::kCPU),
             target(heldout_idx));
    decoder->train();
    return p;
  };

  AdamwLoop loop;
  loop.name = "fast decoder";
  loop.unit = "clips";
  loop.out = job.out;
  loop.prefix = "decoder.";
  loop.steps = job.steps;
  loop.time_budget_s = job.time_budget_s;
  loop.save_every = job.save_every;
  loop.lr = job.lr;
  loop.cosine = true;
  loop.seed = job.seed;
  loop.batch_size = job.batch_size;
  loop.accumulate = job.accumulate;
  loop.device = job.device;
  loop.precision = job.precision;
  loop.extra_columns = {"heldout_psnr"};
  const auto run = run_adamw_loop(
      *decoder, loop, [&] { return models::fast_decoder_checkpoint(*decoder); },
      [&](const LoopStep& s, int64_t batch, torch::Generator& gen) {
        const auto idx = torch::randint(train_n, {batch}, gen, torch::kLong);
        const auto decoded = decoder->decode(clips.latents.index_select(0, idx).to(job.device));
        const auto loss = (decoded - target(idx).to(job.device)).pow(2).mean();
        return AdamwStep{loss, batch, {s.saves ? heldout_psnr() : std::nan("")}};
      });
  decoder->to(torch::kCPU);
  FastDecoderResult r;
  r.steps = run.end_step;
  r.clips = train_n;
  r.heldout_clips = heldout;
  r.loss = run.loss;
  r.heldout_psnr = heldout_psnr();
  r.seconds = run.seconds;
  if (data_parallel().main())
    write_file_atomic(job.out / "train_summary.json", nlohmann::json{{"steps", r.steps},
                                                                     {"clips", r.clips},
                                                                     {"heldout_clips", r.heldout_clips},
                                                                     {"loss", r.loss},
                                                                     {"heldout_psnr_vs_wan", r.heldout_psnr},
                                                                     {"seconds", r.seconds},
                                                                     {"config", decoder->config().to_json()}}
                                                              .dump(2) +
                                                          "\n");
  return r;
}

}  // namespace dojo::train
