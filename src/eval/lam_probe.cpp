#include "eval/lam_probe.h"

#include <algorithm>

#include "core/error.h"
#include "data/episode_store.h"

namespace dojo::eval {

ProbeResult ridge_probe(const torch::Tensor& x_train, const torch::Tensor& y_train,
                        const torch::Tensor& x_test, const torch::Tensor& y_test, double lambda) {
  DOJO_CHECK(x_train.size(0) > 1 && x_test.size(0) > 1, "lam probe: too few samples to fit and evaluate");
  auto xt = x_train.to(torch::kDouble), yt = y_train.to(torch::kDouble);
  auto xm = xt.mean(0), xs = xt.std(0).clamp_min(1e-8), ym = yt.mean(0);
  auto norm = [&](const torch::Tensor& x) { return (x.to(torch::kDouble) - xm) / xs; };
  auto a = norm(xt);
  const int64_t D = a.size(1);
  auto w = torch::linalg_solve(a.t().mm(a) + lambda * a.size(0) * torch::eye(D, torch::kDouble),
                               a.t().mm(yt - ym));
  auto r2 = [&](const torch::Tensor& x, const torch::Tensor& y) {
    auto yd = y.to(torch::kDouble);
    auto pred = norm(x).mm(w) + ym;
    auto sse = (yd - pred).pow(2).sum(0);
    auto sst = (yd - yd.mean(0)).pow(2).sum(0).clamp_min(1e-12);
    return (1 - sse / sst).mean().item<double>();
  };
  ProbeResult r;
  {
    auto yd = y_test.to(torch::kDouble);
    auto sse = (yd - (norm(x_test).mm(w) + ym)).pow(2).sum(0);
    auto per_dim = (1 - sse / (yd - yd.mean(0)).pow(2).sum(0).clamp_min(1e-12)).contiguous();
    r.r2_heldout_per_dim.assign(per_dim.data_ptr<double>(), per_dim.data_ptr<double>() + per_dim.numel());
  }
  r.r2_train = r2(x_train, y_train);
  r.r2_heldout = r2(x_test, y_test);
  r.n_train = x_train.size(0);
  r.n_heldout = x_test.size(0);
  r.target_dims = y_train.size(1);
  return r;
}

ProbePairs probe_deltas(const torch::Tensor& rows, bool commanded) {
  DOJO_CHECK(rows.dim() == 2 && rows.size(0) >= 3, "lam probe: need at least 3 rows of targets per episode");
  const int64_t T = rows.size(0);
  ProbePairs p;
  if (commanded) {
    p.first_pair = 1;
    p.deltas = rows.slice(0, 1, T - 1) - rows.slice(0, 0, T - 2);  // pairs 1..T-2: cmd[t] - cmd[t-1]
  } else {
    p.deltas = rows.slice(0, 1) - rows.slice(0, 0, -1);  // pairs 0..T-2: pose[t+1] - pose[t]
  }
  return p;
}

ProbeTarget parse_probe_target(const std::string& text) {
  if (text == "auto") return ProbeTarget::kAuto;
  if (text == "action") return ProbeTarget::kAction;
  if (text == "motion") return ProbeTarget::kMotion;
  throw UsageError("probe target must be auto, action or motion (got '" + text + "')");
}

nlohmann::json probe_lam(models::LatentActionModel& model, const std::filesystem::path& dataset,
                         const LamProbeOptions& o) {
  const auto store = data::EpisodeStore::open(dataset);
  int64_t n = static_cast<int64_t>(store.size());
  if (o.max_episodes > 0) n = std::min(n, o.max_episodes);
  DOJO_CHECK(n >= 2, "lam probe: " + dataset.string() + " needs at least 2 episodes");
  const int64_t n_train = std::max<int64_t>(1, n * 8 / 10);
  std::vector<torch::Tensor> xs[2], ys[2];
  std::string used;
  for (int64_t i = 0; i < n; ++i) {
    const auto ep = store.load(static_cast<size_t>(i));
    const bool use_action =
        o.target == ProbeTarget::kAction || (o.target == ProbeTarget::kAuto && ep.actions.defined());
    const auto rows = use_action ? ep.actions : ep.hidden_motion;
    DOJO_CHECK(rows.defined(), "lam probe: episode " + store.episode_dir(static_cast<size_t>(i)).string() +
                                   " has no " + (use_action ? "actions" : "hidden_motion"));
    used = use_action ? "action_delta" : "motion_delta";
    // Robot hidden motion is a measured pose; actions and the human hand's rows are commands.
    const bool commanded = use_action || store.info().embodiment == data::Embodiment::kHuman;
    const auto pairs = probe_deltas(rows, commanded);             // [n, K]
    const auto z = models::lam_encode_episode(model, ep.frames);  // [T - 1, latent]
    xs[i >= n_train].push_back(z.narrow(0, pairs.first_pair, pairs.deltas.size(0)));
    ys[i >= n_train].push_back(pairs.deltas);
  }
  const auto r =
      ridge_probe(torch::cat(xs[0]), torch::cat(ys[0]), torch::cat(xs[1]), torch::cat(ys[1]), o.lambda);
  return {{"data", dataset.string()},
          {"embodiment", data::to_string(store.info().embodiment)},
          {"target", used},
          {"target_dims", r.target_dims},
          {"train_pairs", r.n_train},
          {"heldout_pairs", r.n_heldout},
          {"r2_train", r.r2_train},
          {"r2_heldout", r.r2_heldout},
          {"r2_heldout_per_dim", r.r2_heldout_per_dim}};
}

}  // namespace dojo::eval
