// Training and evaluation of small Wan2.1-architecture VAEs (the video tokenizer).
// Loss: reconstruction error (MSE or L1) of the decoded posterior sample (or mean) plus a small KL
// term (the released VAE is a KL-regularised autoencoder; the tiny weight keeps latents near a
// Gaussian without blurring reconstructions). Uses the whole-clip causal path, which equals
// the chunked inference path (tested in wan_vae_test.cpp). Learning rate: linear warm-up, then
// optional cosine decay.
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <filesystem>
#include <functional>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>

#include "core/autocast.h"
#include "data/clip_sampler.h"
#include "models/wan_vae.h"

namespace dojo::train {

class DataParallel;

struct TokenizerTrainOptions {
  int64_t steps = 1000;
  double lr = 1e-3;
  double weight_decay = 0.0;
  double kl_weight = 1e-6;
  double grad_clip = 1.0;        // max global grad norm (0: off)
  bool sample_posterior = true;  // decode mu + sigma * eps (false: decode mu)
  bool l1 = false;               // L1 reconstruction loss instead of MSE
  // Weight of edge_l1 (differences of horizontal and vertical pixel gradients) added to the
  // reconstruction loss. Thin structures (the arm, small objects) are a small part of the pixels,
  // so a pixel loss alone learns the background first; their outlines dominate this term.
  double edge_weight = 0;
  // Weight of hard_pixel_l1 (the mean error of each frame's worst `hard_pixel_fraction` of
  // pixels) added to the reconstruction loss. A 5-pixel cube is under 1 % of a 64x64 frame: the
  // mean loss barely moves when it vanishes, the worst pixels' mean does (docs/benchmarks.md).
  double hard_pixel_weight = 0;
  double hard_pixel_fraction = 0.02;
  int64_t warmup_steps = 0;  // linear lr warm-up from lr / warmup_steps
  bool cosine = false;       // cosine decay from lr to min_lr_fraction * lr after warm-up
  double min_lr_fraction = 0.05;
  int64_t log_every = 50;
  int64_t save_every = 0;                // 0: only at the end (when checkpoint_dir is set)
  std::filesystem::path checkpoint_dir;  // empty: no checkpoints
  bool resume = true;                    // continue from checkpoint_dir when it holds trainer state
  bool progress = true;                  // dojo::Progress line
  nlohmann::json trainer_extra = nlohmann::json::object();  // recorded in the trainer state (e.g. the data)
  // Batches (next_batch(steps + i), i < stats_batches) used after training to fit the latent
  // normalisation constants before the final checkpoint (0: keep the configured constants).
  int64_t stats_batches = 0;
  // Train on random crop x crop windows (a multiple of 8) of every clip, one window per clip and
  // the same for all its frames; 0 = whole frames. The network is convolutional, so a crop costs
  // (crop / size)^2 of a full frame: more optimiser steps for the same compute.
  int64_t crop = 0;
  // Fraction of the run (of the steps, or of the time budget when that ends first) trained on
  // single frames before clips. Images are ~3x cheaper per frame (no temporal taps) and a batch
  // of them spans many more scenes, so colours and shapes are learnt in a fraction of the time;
  // with a model from models::init_frame_by_frame that learning carries over to the clip phase
  // as is. The recommended 0.85 leaves a short clip phase at the low end of the cosine, which
  // learns the temporal taps without undoing the image phase (docs/tokenizer.md). 0: clips only.
  double image_fraction = 0;
  // Image batches [N, 3, 1, H, W] for that phase; unset: every frame of next_batch's clips.
  std::function<torch::Tensor(int64_t)> next_image_batch;
  double time_budget_s = 0;  // stop early (fit stats, checkpoint) after this long; 0: none
  // Micro-batches per step and process (data_parallel.h): next_batch is called this many times a
  // step, gradients accumulate, then are averaged over the ranks.
  int64_t accumulate = 1;
  std::filesystem::path loss_curve;  // CSV "step,recon,kl,seconds,images" when set
  // Where it trains: the model moves there for the run (and back to the CPU after it), batches are
  // moved there; bf16 runs the encoder and decoder under autocast, weights and moments float32.
  torch::Device device = torch::kCPU;
  Precision precision = Precision::kFloat32;
};

// The recipe measured best for small DojoSim tokenizers on CPU (docs/benchmarks.md, "Small
// DojoSim tokenizer"): what `dojo tokenizer train` uses by default. Steps are left to the caller.
TokenizerTrainOptions recommended_tokenizer_options();

// A random size x size window of each clip of `video` [B, C, T, H, W] (the same window for all
// frames of a clip), chosen deterministically from `seed`. Returns the video when it is no larger.
torch::Tensor random_spatial_crop(const torch::Tensor& video, int64_t size, uint64_t seed);

// Learning rate of `step` (0-based) under the options' warm-up / cosine schedule. With a time
// budget the cosine runs over whichever ends first, the steps or the budget: `budget_fraction`
// is the part of the budget used so far (0 when there is none), so a run cut short by its
// budget still ends at the floor instead of at a high learning rate.
double tokenizer_lr(const TokenizerTrainOptions& options, int64_t step, double budget_fraction = 0);

struct TokenizerLoss {
  torch::Tensor total, recon, kl;  // scalars (total has grad); recon: the optimised term
  torch::Tensor mse;               // MSE of the reconstruction (for logs, whatever the loss)
};

// video: [B, 3, T, H, W] in [-1, 1], T = 1 + 4k. The loss terms and weights come from
// `options` (kl_weight, sample_posterior, l1, edge_weight, hard_pixel_weight/_fraction).
TokenizerLoss tokenizer_loss(models::WanVae& vae, const torch::Tensor& video,
                             const TokenizerTrainOptions& options);

// Mean absolute difference of the spatial gradients (neighbour differences along H and along
// W) of two videos [B, C, T, H, W]: zero when they differ by a constant, large at misplaced or
// blurred edges.
torch::Tensor edge_l1(const torch::Tensor& a, const torch::Tensor& b);

// Mean absolute error (averaged over channels) of the `fraction` of pixels of each frame of two
// videos [B, C, T, H, W] where they differ most (at least one pixel a frame).
torch::Tensor hard_pixel_l1(const torch::Tensor& a, const torch::Tensor& b, double fraction);

struct TokenizerTrainResult {
  int64_t steps_done = 0;                // total optimisation steps (including resumed ones)
  double first_loss = 0, last_loss = 0;  // reconstruction MSE of the first / last step of this run
  double seconds = 0;
};

// `next_batch(step)` returns the batch for that step ([B, 3, T, H, W] float in [-1, 1]).
TokenizerTrainResult train_tokenizer(models::WanVae& vae,
                                     const std::function<torch::Tensor(int64_t)>& next_batch,
                                     const TokenizerTrainOptions& options);

// Batch streams over DojoSim-format datasets for train_tokenizer: clips ([B, 3, T, H, W]) and
// single frames ([N, 3, 1, H, W]) drawn from the same episodes, in [-1, 1]. Each stream starts at
// the first step asked of it, so a resumed run continues where it stopped; the image loader is
// only started when the image phase asks for a batch.
struct TokenizerDataset {
  std::filesystem::path dir;
  std::string split = "train";
  double weight = 1.0;  // mixture weight: drawn with probability weight / sum of the weights
};
struct TokenizerBatches {
  std::function<torch::Tensor(int64_t)> clips, images;
};
// Under data parallelism (data_parallel.h) the batches are this process's micro-batches
// (clip_batch and image_batch are global: split over world x accumulate, the same `accumulate` as
// TokenizerTrainOptions::accumulate), each call handing out the next one.
TokenizerBatches tokenizer_batches(const std::vector<TokenizerDataset>& datasets,
                                   const data::ClipConfig& clip, int clip_batch, int image_batch, int workers,
                                   uint64_t seed, int64_t accumulate = 1);

// Per-channel mean/std of mu over the given videos, written into the config used for
// normalisation (a freshly trained model's latents do not follow the published constants).
void fit_latent_stats(models::WanVae& vae, const std::vector<torch::Tensor>& videos);
// The same over every data-parallel rank's videos (data_parallel.h); the plain fit in a world of 1.
void fit_latent_stats(models::WanVae& vae, const std::vector<torch::Tensor>& videos, DataParallel& group);

}  // namespace dojo::train
