// `dojo tokenizer train|encode|eval`: small Wan2.1-architecture VAEs on DojoSim datasets.
#include <sys/resource.h>
#include <CLI/CLI.hpp>

#include <chrono>
#include <cstdio>
#include <memory>
#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/progress.h"
#include "core/safetensors.h"
#include "data/clip_loader.h"
#include "data/episode_source.h"
#include "data/episode_store.h"
#include "eval/tokenizer_eval.h"
#include "io/video.h"
#include "models/wan_vae.h"
#include "train/tokenizer_train.h"

namespace dojo::cli {

namespace {

// Defaults follow train::recommended_tokenizer_options() (measured in docs/benchmarks.md).
struct TrainArgs {
  std::vector<std::string> data;
  std::string out, split = "train", loss = "mse";
  int64_t steps = 2000, save_every = 200, warmup = 0, accumulate = 1;
  // 9 frames (3 latent frames) so the steady-state causal chunk is trained, not only the first
  // two latent frames; world-model clips decode 4 latent frames.
  int batch = 4, image_batch = 16, frames = 9, size = 64, dim = 16, workers = 2, crop = 0;
  double lr = 0, kl = 0, minutes = 0, image_fraction = 0, edge_weight = 0, hard_pixel_weight = 0,
         hard_pixel_fraction = 0;
  bool cosine = true, sample = false;
  uint64_t seed = 0;
  TrainingDeviceArgs device;

  TrainArgs() {
    const auto r = train::recommended_tokenizer_options();
    lr = r.lr, kl = r.kl_weight, warmup = r.warmup_steps, cosine = r.cosine;
    sample = r.sample_posterior, loss = r.l1 ? "l1" : "mse";
    image_fraction = r.image_fraction;
    edge_weight = r.edge_weight;
    hard_pixel_weight = r.hard_pixel_weight;
    hard_pixel_fraction = r.hard_pixel_fraction;
  }
};

struct TokenizerEvalArgs {
  std::string ckpt, data, video, out;
  eval::TokenizerEvalOptions options;
  bool json = false;
};

int run_train(const TrainArgs& a) {
  DOJO_CHECK((a.frames - 1) % 4 == 0, "--frames must be 1 + 4k (got " + std::to_string(a.frames) + ")");
  DOJO_CHECK(a.size % 8 == 0, "--size must be a multiple of 8");
  DOJO_CHECK(a.crop % 8 == 0 && a.crop <= a.size,
             "--crop must be a multiple of 8 and at most --size (got " + std::to_string(a.crop) + ")");
  DOJO_CHECK(a.loss == "mse" || a.loss == "l1", "--loss must be mse or l1 (got " + a.loss + ")");
  models::WanVaeConfig cfg;
  cfg.dim = a.dim;
  // Seeded before the network is drawn: libtorch seeds its default generator differently in every
  // process, and the same --seed must give the same weights (and every data-parallel rank the same).
  torch::manual_seed(a.seed);
  models::WanVae vae(cfg);
  models::init_frame_by_frame(vae);  // a resumed run loads its weights over this
  data::ClipConfig clip;
  clip.num_frames = a.frames;
  clip.strides = {1, 2};
  clip.height = clip.width = a.size;
  std::vector<train::TokenizerDataset> datasets;
  std::vector<WeightedData> data;
  for (const auto& d : a.data) data.push_back(parse_weighted_data(d));
  const auto weights = mixture_weights(data);
  nlohmann::json mixture = nlohmann::json::array();
  for (size_t i = 0; i < data.size(); ++i) {
    // Without weights each dataset is drawn alike (the tokenizer's mixture has always been so).
    datasets.push_back({data[i].dir, a.split, weights.empty() ? 1.0 : weights[i]});
    mixture.push_back({{"data", data[i].dir}, {"weight", datasets.back().weight}});
  }
  const auto batches =
      train::tokenizer_batches(datasets, clip, a.batch, a.image_batch, a.workers, a.seed, a.accumulate);
  auto o = train::recommended_tokenizer_options();
  a.device.set_in(o, "tokenizer train");
  o.steps = a.steps;
  o.lr = a.lr;
  o.kl_weight = a.kl;
  o.warmup_steps = a.warmup;
  o.cosine = a.cosine;
  o.sample_posterior = a.sample;
  o.l1 = a.loss == "l1";
  o.edge_weight = a.edge_weight;
  o.hard_pixel_weight = a.hard_pixel_weight;
  o.hard_pixel_fraction = a.hard_pixel_fraction;
  o.save_every = a.save_every;
  o.crop = a.crop;
  o.image_fraction = a.image_fraction;
  o.next_image_batch = batches.images;
  o.time_budget_s = a.minutes * 60;
  o.accumulate = a.accumulate;
  o.checkpoint_dir = a.out;
  o.trainer_extra = {{"mixture", mixture}};
  o.stats_batches = 8;
  const auto r = train::train_tokenizer(vae, batches.clips, o);
  std::printf("trained %lld steps in %.1f s, recon mse %.5f -> %.5f, checkpoint %s\n",
              static_cast<long long>(r.steps_done), r.seconds, r.first_loss, r.last_loss, a.out.c_str());
  return 0;
}

int run_tokenizer_eval(const TokenizerEvalArgs& a) {
  auto vae = models::load_tokenizer(a.ckpt);
  const auto r = eval::evaluate_tokenizer(vae, a.data, a.options);
  nlohmann::json j = r.to_json();
  j["split"] = a.options.split;
  j["checkpoint"] = a.ckpt;
  if (!a.video.empty()) {
    // Top row: originals side by side; bottom: reconstructions.
    std::vector<at::Tensor> rows = {torch::cat(r.originals, 2), torch::cat(r.reconstructions, 2)};
    io::write_comparison_video(a.video, {torch::cat(rows, 1)}, {"original (top) / reconstruction (bottom)"},
                               data::open_dataset(a.data)->info().fps);
    j["video"] = a.video;
  }
  if (!a.out.empty()) write_file_atomic(a.out, j.dump(2) + "\n");
  if (a.json)
    std::printf("%s\n", j.dump(2).c_str());
  else
    std::printf("PSNR %.2f dB  SSIM %.4f  over %d clips of %d frames (%s)\n", r.psnr, r.ssim, r.clips,
                r.frames, a.options.split.c_str());
  return 0;
}

int run_encode(const std::string& ckpt, const std::string& dir, const std::string& out,
               const std::string& split) {
  auto vae = models::load_tokenizer(ckpt);
  const auto store = data::EpisodeStore::open(dir);
  const auto indices = store.split_indices(split);
  std::filesystem::create_directories(out);
  nlohmann::json index = {{"checkpoint", ckpt},
                          {"dataset", dir},
                          {"normalised", true},
                          {"temporal_factor", 4},
                          {"spatial_factor", vae->config().spatial_factor()},
                          {"episodes", nlohmann::json::array()}};
  Progress progress("tokenizer encode", static_cast<int64_t>(indices.size()), "episode");
  torch::NoGradGuard no_grad;
  for (size_t i : indices) {
    const auto& entry = store.info().episodes[i];
    const auto frames = store.load(i).frames;  // [T, H, W, 3]
    const int64_t t = models::wan_pixel_frames(models::wan_latent_frames(frames.size(0)));
    // Streamed in chunks so long episodes encode with bounded memory.
    models::WanVaeStreamEncoder enc(vae);
    std::vector<torch::Tensor> mus;
    for (int64_t s = 0; s < t; s += 16)
      mus.push_back(
          enc.push(models::video_to_model(frames.narrow(0, s, std::min<int64_t>(16, t - s)).unsqueeze(0))));
    const auto z = vae->normalize(torch::cat(mus, 2))[0].contiguous();  // [z, T_lat, h, w]
    save_safetensors(std::filesystem::path(out) / (entry.id + ".safetensors"), {{"z", z}},
                     {{"episode", entry.id}, {"pixel_frames", std::to_string(t)}});
    index["episodes"].push_back(
        {{"id", entry.id}, {"split", entry.split}, {"pixel_frames", t}, {"latent_frames", z.size(1)}});
    progress.advance();
  }
  progress.finish();
  write_file_atomic(std::filesystem::path(out) / "index.json", index.dump(2) + "\n");
  std::printf("encoded %zu episodes into %s\n", indices.size(), out.c_str());
  return 0;
}

long peak_rss_mib() {
  struct rusage u;
  getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss / 1024;  // Linux reports KiB
}

// Encode / decode throughput of the chunked streaming path and the decoder cache size as the
// rollout grows (it must stay flat: bounded memory).
int run_bench(int dim, int height, int width, int frames, const std::string& ckpt) {
  torch::NoGradGuard no_grad;
  models::WanVaeConfig cfg;
  cfg.dim = dim;
  models::WanVae vae = ckpt.empty() ? models::WanVae(cfg) : models::load_tokenizer(ckpt);
  vae->eval();
  const auto x = torch::rand({1, 3, frames, height, width}) * 2 - 1;
  using clock = std::chrono::steady_clock;
  auto t0 = clock::now();
  const auto mu = vae->encode(x).mu;
  const double enc_s = std::chrono::duration<double>(clock::now() - t0).count();
  models::WanVaeStreamDecoder dec(vae);
  std::vector<int64_t> cache_bytes;
  t0 = clock::now();
  int64_t out_frames = 0;
  for (int64_t i = 0; i < mu.size(2); ++i) {
    out_frames += dec.push(mu.narrow(2, i, 1)).size(2);
    cache_bytes.push_back(dec.cache().bytes());
  }
  const double dec_s = std::chrono::duration<double>(clock::now() - t0).count();
  nlohmann::json j = {{"dim", vae->config().dim},
                      {"height", height},
                      {"width", width},
                      {"frames", frames},
                      {"threads", torch::get_num_threads()},
                      {"encode_fps", frames / enc_s},
                      {"decode_fps", out_frames / dec_s},
                      {"decoder_cache_bytes_per_latent", cache_bytes},
                      {"peak_rss_mib", peak_rss_mib()}};
  std::printf("%s\n", j.dump(2).c_str());
  return 0;
}

}  // namespace

void register_tokenizer(CLI::App& app) {
  auto* tok =
      app.add_subcommand("tokenizer", "Train, evaluate and run the Wan2.1-architecture video tokenizer");
  tok->require_subcommand(1);
  register_fast_decoder(*tok);

  auto* train_cmd =
      tok->add_subcommand("train", "Train a small VAE on DojoSim datasets (resumes from --out)");
  auto ta = std::make_shared<TrainArgs>();
  add_data_option(train_cmd, ta->data,
                  "DIR:WEIGHT draws that dataset in proportion to WEIGHT (a dataset without one weighs 1; "
                  "with none, each dataset alike)")
      ->required();
  add_out_option(train_cmd, ta->out, "checkpoint directory")->required();
  add_split_option(train_cmd, ta->split);
  train_cmd->add_option("--steps", ta->steps, "Optimisation steps")->capture_default_str();
  train_cmd->add_option("--batch", ta->batch, "Clips per batch")->capture_default_str();
  add_accumulate_option(train_cmd, ta->accumulate);
  train_cmd->add_option("--frames", ta->frames, "Frames per clip (1 + 4k)")->capture_default_str();
  train_cmd
      ->add_option("--image-fraction", ta->image_fraction,
                   "Part of the run (steps or --minutes) trained on single frames before clips")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  train_cmd->add_option("--image-batch", ta->image_batch, "Frames per batch in the image phase")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  train_cmd->add_option("--size", ta->size, "Clip height and width (multiple of 8)")->capture_default_str();
  train_cmd->add_option("--dim", ta->dim, "Base width (released: 96)")->capture_default_str();
  train_cmd
      ->add_option("--crop", ta->crop, "Train on random CROPxCROP windows of the clips (0: whole frames)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  train_cmd->add_option("--minutes", ta->minutes, "Stop after this many minutes (0: run all --steps)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  train_cmd->add_option("--lr", ta->lr, "AdamW learning rate")->capture_default_str();
  train_cmd->add_option("--kl", ta->kl, "KL weight")->capture_default_str();
  train_cmd->add_option("--warmup", ta->warmup, "Linear lr warm-up steps")->capture_default_str();
  train_cmd->add_flag("--cosine,!--no-cosine", ta->cosine, "Cosine lr decay to 5% after warm-up")
      ->capture_default_str();
  train_cmd->add_option("--loss", ta->loss, "Reconstruction loss: mse | l1")->capture_default_str();
  train_cmd
      ->add_option("--edge-weight", ta->edge_weight,
                   "Weight of the edge term (L1 of pixel-gradient differences) added to the loss")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  train_cmd
      ->add_option(
          "--hard-pixel-weight", ta->hard_pixel_weight,
          "Weight of the mean error of each frame's worst pixels (--hard-pixel-fraction) added to the "
          "loss: small objects a pixel loss lets vanish")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  train_cmd
      ->add_option("--hard-pixel-fraction", ta->hard_pixel_fraction,
                   "Share of each frame's pixels that term averages")
      ->check(CLI::Range(1e-4, 1.0))
      ->capture_default_str();
  train_cmd
      ->add_flag("--sample-posterior,!--decode-mean", ta->sample,
                 "Train on a posterior sample (default: decode the posterior mean)")
      ->capture_default_str();
  train_cmd->add_option("--save-every", ta->save_every, "Checkpoint interval in steps")
      ->capture_default_str();
  add_workers_option(train_cmd, ta->workers);
  add_seed_option(train_cmd, ta->seed);
  ta->device.add_to(train_cmd);
  train_cmd->callback([=] { set_action([=] { return run_train(*ta); }); });

  auto* eval_cmd =
      tok->add_subcommand("eval", "Reconstruction PSNR/SSIM on a split, optional side-by-side video");
  auto ea = std::make_shared<TokenizerEvalArgs>();
  add_checkpoint_option(eval_cmd, ea->ckpt, "the tokenizer")->required();
  add_data_option(eval_cmd, ea->data)->required();
  add_split_option(eval_cmd, ea->options.split);
  eval_cmd->add_option("--clips", ea->options.clips, "Clips to evaluate")->capture_default_str();
  eval_cmd->add_option("--frames", ea->options.frames, "Frames per clip (1 + 4k)")->capture_default_str();
  eval_cmd->add_option("--size", ea->options.size, "Clip size (0: dataset size)")->capture_default_str();
  eval_cmd->add_option("--video", ea->video, "Write original vs reconstruction .mp4 here");
  add_out_option(eval_cmd, ea->out, "JSON file for the result");
  add_seed_option(eval_cmd, ea->options.seed);
  add_json_option(eval_cmd, ea->json);
  eval_cmd->callback([=] { set_action([=] { return run_tokenizer_eval(*ea); }); });

  auto* enc_cmd =
      tok->add_subcommand("encode", "Cache normalised latents of every episode (one .safetensors each)");
  auto ckpt = std::make_shared<std::string>(), dir = std::make_shared<std::string>(),
       out = std::make_shared<std::string>(), split = std::make_shared<std::string>("all");
  add_checkpoint_option(enc_cmd, *ckpt, "the tokenizer")->required();
  add_data_option(enc_cmd, *dir)->required();
  add_out_option(enc_cmd, *out, "latent cache directory")->required();
  add_split_option(enc_cmd, *split);
  enc_cmd->callback([=] { set_action([=] { return run_encode(*ckpt, *dir, *out, *split); }); });

  auto* bench_cmd =
      tok->add_subcommand("bench", "Encode/decode frames/s, peak memory, decoder cache vs rollout length");
  auto bdim = std::make_shared<int>(96), bh = std::make_shared<int>(64), bw = std::make_shared<int>(64),
       bt = std::make_shared<int>(13);
  auto bckpt = std::make_shared<std::string>();
  bench_cmd->add_option("--dim", *bdim, "Base width of a random-init model (96: released)")
      ->capture_default_str();
  bench_cmd->add_option("--height", *bh, "Frame height")->capture_default_str();
  bench_cmd->add_option("--width", *bw, "Frame width")->capture_default_str();
  bench_cmd->add_option("--frames", *bt, "Frames (1 + 4k)")->capture_default_str();
  add_checkpoint_option(bench_cmd, *bckpt, "a trained tokenizer to measure instead of a random model");
  bench_cmd->callback([=] { set_action([=] { return run_bench(*bdim, *bh, *bw, *bt, *bckpt); }); });
}

}  // namespace dojo::cli
