// `dojo tokenizer fast-decoder`: distil the tokenizer's Wan decoder into the fast streaming decoder
// (train/fast_decoder_train.h) for `wm stream --fast-decoder`.
#include <CLI/CLI.hpp>

#include <cstdio>
#include <memory>

#include "cli/commands.h"
#include "cli/options.h"
#include "train/fast_decoder_train.h"

namespace dojo::cli {
namespace {

struct FastDecoderArgs {
  std::string tokenizer, split = "train", out;
  std::vector<std::string> data;
  int64_t steps = 2000, save_every = 500, hop = 4, max_clips = 0;
  int batch = 8;
  int64_t accumulate = 1;
  double lr = 1e-3, minutes = 0;
  uint64_t seed = 0;
  TrainingDeviceArgs device;
};

int run_fast_decoder(const FastDecoderArgs& a) {
  train::FastDecoderJob job;
  a.device.set_in(job, "fast decoder");
  for (const auto& d : a.data) {
    train::LatentCacheSpec spec;
    spec.dataset = d;
    spec.split = a.split;
    spec.tokenizer = a.tokenizer;
    spec.hop = a.hop;
    spec.max_clips = a.max_clips;
    spec.strides = {1};
    job.data.push_back(spec);
  }
  job.out = a.out;
  job.batch_size = a.batch;
  job.accumulate = a.accumulate;
  job.steps = a.steps;
  job.lr = a.lr;
  job.time_budget_s = a.minutes * 60;
  job.save_every = a.save_every;
  job.seed = a.seed;
  // Convolutions only: every thread (one left a core idle: 1.73 against 2.66 steps/s on 2 cores,
  // docs/benchmarks.md).
  const auto r = train::run_fast_decoder_training(job);
  std::printf(
      "fast decoder: %lld steps on %lld clips, loss %.5f, held-out PSNR against the Wan decoder %.2f dB "
      "(%lld clips)\ncheckpoint %s/checkpoint (use it with `dojo wm stream --fast-decoder`)\n",
      static_cast<long long>(r.steps), static_cast<long long>(r.clips), r.loss, r.heldout_psnr,
      static_cast<long long>(r.heldout_clips), a.out.c_str());
  return 0;
}

}  // namespace

void register_fast_decoder(CLI::App& tokenizer) {
  auto a = std::make_shared<FastDecoderArgs>();
  auto* cmd = tokenizer.add_subcommand(
      "fast-decoder", "Distil the tokenizer's decoder into a fast streaming decoder (resumes from --out)");
  cmd->add_option("--tokenizer", a->tokenizer, "Tokenizer checkpoint whose decoder is distilled")->required();
  add_data_option(cmd, a->data)->required();
  add_split_option(cmd, a->split);
  add_out_option(cmd, a->out, "directory: checkpoint/, loss.csv")->required();
  cmd->add_option("--steps", a->steps, "Optimisation steps")->capture_default_str();
  cmd->add_option("--minutes", a->minutes, "Wall-clock budget (0: none)");
  cmd->add_option("--batch,-b", a->batch, "Clips per step")->capture_default_str();
  add_accumulate_option(cmd, a->accumulate);
  cmd->add_option("--lr", a->lr, "AdamW peak learning rate")->capture_default_str();
  cmd->add_option("--hop", a->hop, "Clip start stride in frames")->capture_default_str();
  cmd->add_option("--max-clips", a->max_clips, "Clips per dataset (0: all)")->capture_default_str();
  cmd->add_option("--save-every", a->save_every, "Checkpoint every N steps")->capture_default_str();
  add_seed_option(cmd, a->seed);
  a->device.add_to(cmd);
  cmd->callback([a] { set_action([a] { return run_fast_decoder(*a); }); });
}

}  // namespace dojo::cli
