// `dojo lam`: train the latent action model, label datasets with latent actions, probe them.
#include <torch/torch.h>
#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <tuple>

#include "cli/commands.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/runtime.h"
#include "core/state_dict.h"
#include "data/episode_store.h"
#include "io/video.h"
#include "models/lam.h"
#include "train/lam_train.h"

namespace dojo::cli {
namespace {

// "DIR" or "DIR:WEIGHT".
std::pair<std::filesystem::path, double> parse_dataset(const std::string& text) {
  const auto colon = text.rfind(':');
  if (colon == std::string::npos || colon == 0) return {text, 1.0};
  try {
    size_t used = 0;
    const double w = std::stod(text.substr(colon + 1), &used);
    if (used != text.size() - colon - 1 || !(w > 0)) throw std::invalid_argument("weight");
    return {text.substr(0, colon), w};
  } catch (const std::exception&) {
    throw UsageError("--data must look like DIR or DIR:WEIGHT with WEIGHT > 0, got '" + text + "'");
  }
}

void add_train(CLI::App& lam) {
  auto* cmd = lam.add_subcommand(
      "train",
      "Train the latent action model on frame pairs (random skip 1-4) of a dataset mixture. "
      "Resumes from OUT/checkpoint; writes OUT/loss.csv.");
  auto job = std::make_shared<train::LamTrainJob>();
  auto data = std::make_shared<std::vector<std::string>>();
  auto size = std::make_shared<std::string>("small");
  cmd->add_option("--data,-d", *data, "Dataset directory, optionally DIR:WEIGHT (repeat for a mixture)")
      ->required();
  cmd->add_option("--out,-o", job->out, "Output directory")->required();
  cmd->add_option("--model", *size, "Model size: tiny, small or released")
      ->check(CLI::IsMember({"tiny", "small", "released"}))
      ->capture_default_str();
  cmd->add_option("--steps", job->steps, "Total optimisation steps")->capture_default_str();
  cmd->add_option("--batch,-b", job->batch_size, "Frame pairs per step")->capture_default_str();
  cmd->add_option("--lr", job->options.lr, "AdamW learning rate")->capture_default_str();
  cmd->add_option("--weight-decay", job->options.weight_decay, "AdamW weight decay")->capture_default_str();
  cmd->add_option("--beta", job->options.beta, "KL weight")->capture_default_str();
  cmd->add_option("--grad-clip", job->options.grad_clip, "Gradient norm clip (0 = off)")
      ->capture_default_str();
  cmd->add_option("--brightness", job->options.brightness, "Brightness jitter amplitude")
      ->capture_default_str();
  cmd->add_option("--save-every", job->save_every, "Checkpoint interval in steps")->capture_default_str();
  cmd->add_option("--workers,-j", job->workers, "Data loader workers")->capture_default_str();
  cmd->add_option("--seed", job->seed, "Random seed")->capture_default_str();
  cmd->callback([=] {
    set_action([=] {
      for (const auto& d : *data) job->datasets.push_back(parse_dataset(d));
      job->model = *size == "tiny"    ? models::LamConfig::tiny()
                   : *size == "small" ? models::LamConfig::small()
                                      : models::LamConfig::released();
      DOJO_CHECK(job->steps > 0 && job->batch_size > 0 && job->save_every > 0,
                 "lam train: --steps, --batch and --save-every must be positive");
      const auto s = [&] {
        ScopedThreads matmul_bound(matmul_bound_command_threads("lam train", /*on_cuda=*/false));
        return train::run_lam_training(*job);
      }();
      std::printf("lam train: step %lld loss %.6g mse %.6g kl %.6g psnr %.2f dB; checkpoint %s\n",
                  static_cast<long long>(job->steps), s.loss, s.mse, s.kl, s.psnr,
                  (job->out / "checkpoint").string().c_str());
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
  cmd->add_option("--ckpt,-c", *ckpt, "LAM checkpoint directory")->required();
  cmd->add_option("--data,-d", *dataset, "Dataset directory")->required();
  cmd->add_option("--out,-o", *out, "Output directory (default DATASET/lam_latents)");
  cmd->add_option("--batch,-b", *batch, "Frame pairs per forward pass")->capture_default_str();
  cmd->callback([=] {
    set_action([=] {
      auto model = train::load_lam(*ckpt);
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
  auto lambda = std::make_shared<double>(1e-3);
  auto max_episodes = std::make_shared<int64_t>(0);
  auto json = std::make_shared<bool>(false);
  cmd->add_option("--ckpt,-c", *ckpt, "LAM checkpoint directory")->required();
  cmd->add_option("--data,-d", *data, "Dataset directory (repeat for several)")->required();
  cmd->add_option("--target", *target, "auto (actions when present, else hidden motion), action or motion")
      ->check(CLI::IsMember({"auto", "action", "motion"}))
      ->capture_default_str();
  cmd->add_option("--lambda", *lambda, "Ridge strength (relative to the sample count)")
      ->capture_default_str();
  cmd->add_option("--max-episodes", *max_episodes, "Use at most this many episodes per dataset (0 = all)");
  cmd->add_flag("--json", *json, "Print the result as JSON");
  cmd->callback([=] {
    set_action([=] {
      auto model = train::load_lam(*ckpt);
      nlohmann::json result = {{"ckpt", *ckpt}, {"datasets", nlohmann::json::array()}};
      for (const auto& dir : *data) {
        auto store = data::EpisodeStore::open(dir);
        int64_t n = static_cast<int64_t>(store.size());
        if (*max_episodes > 0) n = std::min(n, *max_episodes);
        DOJO_CHECK(n >= 2, "lam probe: " + dir + " needs at least 2 episodes");
        const int64_t n_train = std::max<int64_t>(1, n * 8 / 10);
        std::vector<torch::Tensor> xs[2], ys[2];
        std::string used;
        for (int64_t i = 0; i < n; ++i) {
          auto ep = store.load(static_cast<size_t>(i));
          const bool use_action = *target == "action" || (*target == "auto" && ep.actions.defined());
          const auto src = use_action ? ep.actions : ep.hidden_motion;
          DOJO_CHECK(src.defined(), "lam probe: episode " + store.episode_dir(i).string() + " has no " +
                                        (use_action ? "actions" : "hidden_motion"));
          used = use_action ? "action_delta" : "motion_delta";
          // Robot hidden motion is a measured pose; actions and the human hand's rows are commands.
          const bool commanded = use_action || store.info().embodiment == data::Embodiment::kHuman;
          const auto pairs = train::probe_deltas(src, commanded);      // [n, K]
          const auto z = train::lam_encode_episode(model, ep.frames);  // [T - 1, latent]
          xs[i >= n_train].push_back(z.narrow(0, pairs.first_pair, pairs.deltas.size(0)));
          ys[i >= n_train].push_back(pairs.deltas);
        }
        const auto r = train::ridge_probe(torch::cat(xs[0]), torch::cat(ys[0]), torch::cat(xs[1]),
                                          torch::cat(ys[1]), *lambda);
        result["datasets"].push_back({{"data", dir},
                                      {"embodiment", data::to_string(store.info().embodiment)},
                                      {"target", used},
                                      {"target_dims", r.target_dims},
                                      {"train_pairs", r.n_train},
                                      {"heldout_pairs", r.n_heldout},
                                      {"r2_train", r.r2_train},
                                      {"r2_heldout", r.r2_heldout},
                                      {"r2_heldout_per_dim", r.r2_heldout_per_dim}});
      }
      if (*json) {
        std::printf("%s\n", result.dump(2).c_str());
      } else {
        for (const auto& d : result["datasets"])
          std::printf("%s (%s, %s): R^2 train %.3f, held-out %.3f (%lld / %lld pairs)\n",
                      d["data"].get<std::string>().c_str(), d["embodiment"].get<std::string>().c_str(),
                      d["target"].get<std::string>().c_str(), d["r2_train"].get<double>(),
                      d["r2_heldout"].get<double>(), static_cast<long long>(d["train_pairs"].get<int64_t>()),
                      static_cast<long long>(d["heldout_pairs"].get<int64_t>()));
      }
      return 0;
    });
  });
}

void add_retrieve(CLI::App& lam) {
  auto* cmd = lam.add_subcommand(
      "retrieve",
      "For query frame pairs from one dataset, find the nearest latent actions among the pairs of other "
      "datasets "
      "and write an image grid: each row is a query pair followed by its k nearest pairs.");
  auto ckpt = std::make_shared<std::string>();
  auto query = std::make_shared<std::string>();
  auto data = std::make_shared<std::vector<std::string>>();
  auto out = std::make_shared<std::string>();
  auto queries = std::make_shared<int64_t>(4);
  auto k = std::make_shared<int64_t>(3);
  auto max_episodes = std::make_shared<int64_t>(0);
  cmd->add_option("--ckpt,-c", *ckpt, "LAM checkpoint directory")->required();
  cmd->add_option("--query,-q", *query, "Dataset the query pairs come from")->required();
  cmd->add_option("--data,-d", *data, "Dataset(s) to search (repeat)")->required();
  cmd->add_option("--out,-o", *out, "Output PNG")->required();
  cmd->add_option("--queries,-n", *queries, "Number of query pairs (evenly spaced over the dataset)")
      ->capture_default_str();
  cmd->add_option("--k", *k, "Neighbours per query")->capture_default_str();
  cmd->add_option("--max-episodes", *max_episodes, "Use at most this many episodes per dataset (0 = all)");
  cmd->callback([=] {
    set_action([=] {
      DOJO_CHECK(*queries > 0 && *k > 0, "lam retrieve: --queries and --k must be positive");
      auto model = train::load_lam(*ckpt);
      const auto& c = model->config;
      struct Pairs {
        std::vector<torch::Tensor> frames;               // per episode [T, h, w, 3] uint8 at model size
        std::vector<std::pair<int64_t, int64_t>> index;  // (episode, t) per row
        torch::Tensor mu;                                // [N, latent]
      };
      auto encode_dataset = [&](const std::string& dir) {
        auto store = data::EpisodeStore::open(dir);
        int64_t n = static_cast<int64_t>(store.size());
        if (*max_episodes > 0) n = std::min(n, *max_episodes);
        Pairs p;
        std::vector<torch::Tensor> mus;
        for (int64_t e = 0; e < n; ++e) {
          auto f = io::resize_center_crop(store.load(static_cast<size_t>(e)).frames, c.height, c.width);
          const auto mu = train::lam_encode_episode(model, f);
          for (int64_t t = 0; t < mu.size(0); ++t)
            p.index.emplace_back(static_cast<int64_t>(p.frames.size()), t);
          p.frames.push_back(f);
          mus.push_back(mu);
        }
        DOJO_CHECK(!p.index.empty(), "lam retrieve: " + dir + " has no frame pairs");
        p.mu = torch::cat(mus);
        return p;
      };
      const auto q = encode_dataset(*query);
      std::vector<Pairs> db;
      for (const auto& d : *data) db.push_back(encode_dataset(d));
      const int64_t pad = 4;
      auto pair_image = [&](const Pairs& p, int64_t row) {
        const auto [e, t] = p.index[static_cast<size_t>(row)];
        auto gap = torch::full({c.height, 1, 3}, 255, torch::kByte);
        return torch::cat({p.frames[e][t], gap, p.frames[e][t + 1]}, 1);  // [h, 2w + 1, 3]
      };
      std::vector<torch::Tensor> rows;
      const int64_t nq = std::min<int64_t>(*queries, static_cast<int64_t>(q.index.size()));
      for (int64_t i = 0; i < nq; ++i) {
        const int64_t qi = i * static_cast<int64_t>(q.index.size()) / nq;
        std::vector<torch::Tensor> cells{pair_image(q, qi)};
        // Nearest latents over all searched datasets together (Euclidean on z_mu).
        std::vector<std::tuple<double, size_t, int64_t>> cand;
        for (size_t d = 0; d < db.size(); ++d) {
          const auto dist = (db[d].mu - q.mu[qi]).pow(2).sum(1);
          const auto kk = std::min<int64_t>(*k, dist.size(0));
          const auto top = std::get<1>(dist.topk(kk, 0, /*largest=*/false));
          for (int64_t j = 0; j < kk; ++j) {
            const auto r = top[j].item<int64_t>();
            cand.emplace_back(dist[r].item<double>(), d, r);
          }
        }
        std::sort(cand.begin(), cand.end());
        for (int64_t j = 0; j < std::min<int64_t>(*k, static_cast<int64_t>(cand.size())); ++j) {
          cells.push_back(torch::zeros({c.height, pad * 2, 3}, torch::kByte));
          cells.push_back(pair_image(db[std::get<1>(cand[j])], std::get<2>(cand[j])));
        }
        rows.push_back(torch::cat(cells, 1));
        rows.push_back(torch::zeros({pad, rows.back().size(1), 3}, torch::kByte));
      }
      rows.pop_back();
      io::write_png(*out, torch::cat(rows, 0).contiguous());
      std::printf("lam retrieve: %lld queries x %lld neighbours -> %s\n", static_cast<long long>(nq),
                  static_cast<long long>(*k), out->c_str());
      return 0;
    });
  });
}

}  // namespace

void register_lam(CLI::App& app) {
  auto* lam = app.add_subcommand("lam", "Latent action model: train, label, probe, retrieve");
  lam->require_subcommand(1);
  add_train(*lam);
  add_label(*lam);
  add_probe(*lam);
  add_retrieve(*lam);
}

}  // namespace dojo::cli
