// `dojo lam`: train the latent action model, label datasets with latent actions, probe them,
// retrieve neighbours across datasets.
#include <CLI/CLI.hpp>

#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/error.h"
#include "core/runtime.h"
#include "eval/lam_probe.h"
#include "eval/lam_retrieval.h"
#include "io/video.h"
#include "models/lam.h"
#include "train/lam_label.h"
#include "train/lam_train.h"

namespace dojo::cli {
namespace {

void add_lam_train(CLI::App& lam) {
  auto* cmd = lam.add_subcommand(
      "train",
      "Train the latent action model on frame pairs (random skip 1-4) of a dataset mixture. "
      "Resumes from OUT/checkpoint; writes OUT/loss.csv.");
  auto job = std::make_shared<train::LamTrainJob>();
  auto data = std::make_shared<std::vector<std::string>>();
  auto size = std::make_shared<std::string>("small");
  auto out = std::make_shared<std::string>();
  auto minutes = std::make_shared<double>(0);
  add_data_option(cmd, *data, "DIR:WEIGHT gives the dataset that share of the mixture")->required();
  add_out_option(cmd, *out, "directory for checkpoint/ and loss.csv")->required();
  cmd->add_option("--model", *size, "Model size: tiny, small or released")
      ->check(CLI::IsMember({"tiny", "small", "released"}))
      ->capture_default_str();
  cmd->add_option("--steps", job->steps, "Total optimisation steps")->capture_default_str();
  cmd->add_option("--minutes", *minutes, "Stop (and checkpoint) after this many minutes; 0 = no limit")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--batch,-b", job->batch_size, "Frame pairs per step")->capture_default_str();
  add_accumulate_option(cmd, job->accumulate);
  cmd->add_option("--lr", job->options.lr, "AdamW learning rate")->capture_default_str();
  cmd->add_option("--weight-decay", job->options.weight_decay, "AdamW weight decay")->capture_default_str();
  cmd->add_option("--beta", job->options.beta, "KL weight")->capture_default_str();
  cmd->add_option("--grad-clip", job->options.grad_clip, "Gradient norm clip (0 = off)")
      ->capture_default_str();
  cmd->add_option("--brightness", job->options.brightness, "Brightness jitter amplitude")
      ->capture_default_str();
  cmd->add_option("--save-every", job->save_every, "Checkpoint interval in steps")->capture_default_str();
  add_workers_option(cmd, job->workers);
  add_seed_option(cmd, job->seed);
  auto device = std::make_shared<TrainingDeviceArgs>();
  device->add_to(cmd);
  cmd->callback([=] {
    set_action([=] {
      for (const auto& d : *data) {
        const auto parsed = parse_weighted_data(d);
        job->datasets.emplace_back(parsed.dir, parsed.weight);
      }
      device->set_in(*job, "lam train");
      job->out = *out;
      job->time_budget_s = *minutes * 60.0;
      job->model = *size == "tiny"    ? models::LamConfig::tiny()
                   : *size == "small" ? models::LamConfig::small()
                                      : models::LamConfig::released();
      DOJO_CHECK(job->steps > 0 && job->batch_size > 0 && job->save_every > 0,
                 "lam train: --steps, --batch and --save-every must be positive");
      const auto s = [&] {
        ScopedThreads matmul_bound(matmul_bound_command_threads("lam train", /*on_cuda=*/false));
        return train::run_lam_training(*job);
      }();
      std::printf("lam train: loss %.6g mse %.6g kl %.6g psnr %.2f dB at the last step; checkpoint %s\n",
                  s.loss, s.mse, s.kl, s.psnr, (job->out / "checkpoint").string().c_str());
      return 0;
    });
  });
}

void add_label(CLI::App& lam) {
  auto* cmd = lam.add_subcommand("label",
                                 "Write the latent action of every consecutive frame pair of a dataset "
                                 "(DATASET/lam_latents/<episode>.safetensors, z_mu [T-1, 32]).");
  auto ckpt = std::make_shared<std::string>();
  auto dataset = std::make_shared<std::string>();
  auto out = std::make_shared<std::string>();
  auto batch = std::make_shared<int64_t>(16);
  add_checkpoint_option(cmd, *ckpt, "the latent action model")->required();
  add_data_option(cmd, *dataset)->required();
  add_out_option(cmd, *out, "directory for the latents (default DATASET/lam_latents)");
  cmd->add_option("--batch,-b", *batch, "Frame pairs per forward pass")->capture_default_str();
  cmd->callback([=] {
    set_action([=] {
      auto model = models::load_lam(*ckpt);
      const auto s = train::label_lam_dataset(model, *dataset, *out, *batch);
      std::printf("lam label: %lld episodes, %lld new pairs in %.1f s\n", static_cast<long long>(s.episodes),
                  static_cast<long long>(s.pairs), s.seconds);
      return 0;
    });
  });
}

void add_probe(CLI::App& lam) {
  auto* cmd = lam.add_subcommand(
      "probe",
      "Fit a ridge probe from latent actions to ground-truth per-step deltas (robot: action deltas; human: "
      "hidden hand-motion deltas) on the first 80% of episodes and report R^2 on the held-out rest.");
  auto ckpt = std::make_shared<std::string>();
  auto data = std::make_shared<std::vector<std::string>>();
  auto target = std::make_shared<std::string>("auto");
  auto options = std::make_shared<eval::LamProbeOptions>();
  auto json = std::make_shared<bool>(false);
  add_checkpoint_option(cmd, *ckpt, "the latent action model")->required();
  add_data_option(cmd, *data)->required();
  cmd->add_option("--target", *target, "auto (actions when present, else hidden motion), action or motion")
      ->check(CLI::IsMember({"auto", "action", "motion"}))
      ->capture_default_str();
  cmd->add_option("--lambda", options->lambda, "Ridge strength (relative to the sample count)")
      ->capture_default_str();
  cmd->add_option("--max-episodes", options->max_episodes,
                  "Use at most this many episodes per dataset (0 = all)");
  add_json_option(cmd, *json);
  cmd->callback([=] {
    set_action([=] {
      options->target = eval::parse_probe_target(*target);
      auto model = models::load_lam(*ckpt);
      nlohmann::json result = {{"ckpt", *ckpt}, {"datasets", nlohmann::json::array()}};
      for (const auto& dir : *data) result["datasets"].push_back(eval::probe_lam(model, dir, *options));
      if (*json) {
        std::printf("%s\n", result.dump(2).c_str());
        return 0;
      }
      for (const auto& d : result["datasets"])
        std::printf("%s (%s, %s): R^2 train %.3f, held-out %.3f (%lld / %lld pairs)\n",
                    d["data"].get<std::string>().c_str(), d["embodiment"].get<std::string>().c_str(),
                    d["target"].get<std::string>().c_str(), d["r2_train"].get<double>(),
                    d["r2_heldout"].get<double>(), static_cast<long long>(d["train_pairs"].get<int64_t>()),
                    static_cast<long long>(d["heldout_pairs"].get<int64_t>()));
      return 0;
    });
  });
}

void add_retrieve(CLI::App& lam) {
  auto* cmd = lam.add_subcommand(
      "retrieve",
      "For query frame pairs from one dataset, find the nearest latent actions among the pairs of other "
      "datasets and write an image grid: each row is a query pair followed by its k nearest pairs.");
  auto ckpt = std::make_shared<std::string>();
  auto query = std::make_shared<std::string>();
  auto data = std::make_shared<std::vector<std::string>>();
  auto out = std::make_shared<std::string>();
  auto options = std::make_shared<eval::LamRetrievalOptions>();
  add_checkpoint_option(cmd, *ckpt, "the latent action model")->required();
  cmd->add_option("--query,-q", *query, "Dataset the query pairs come from")->required();
  add_data_option(cmd, *data, "the datasets searched for neighbours")->required();
  add_out_option(cmd, *out, "PNG image")->required();
  cmd->add_option("--queries,-n", options->queries, "Number of query pairs (evenly spaced over the dataset)")
      ->capture_default_str();
  cmd->add_option("--k", options->k, "Neighbours per query")->capture_default_str();
  cmd->add_option("--max-episodes", options->max_episodes,
                  "Use at most this many episodes per dataset (0 = all)");
  cmd->callback([=] {
    set_action([=] {
      auto model = models::load_lam(*ckpt);
      const std::vector<std::filesystem::path> search(data->begin(), data->end());
      io::write_png(*out, eval::lam_retrieval_grid(model, *query, search, *options));
      std::printf("lam retrieve: %lld queries x %lld neighbours -> %s\n",
                  static_cast<long long>(options->queries), static_cast<long long>(options->k), out->c_str());
      return 0;
    });
  });
}

}  // namespace

void register_lam(CLI::App& app) {
  auto* lam = app.add_subcommand("lam", "Latent action model: train, label, probe, retrieve");
  lam->require_subcommand(1);
  add_lam_train(*lam);
  add_label(*lam);
  add_probe(*lam);
  add_retrieve(*lam);
}

}  // namespace dojo::cli
