#include "eval/lam_retrieval.h"

#include <algorithm>
#include <tuple>

#include "core/error.h"
#include "data/episode_store.h"
#include "io/frame_ops.h"

namespace dojo::eval {
namespace {

// Every consecutive frame pair of a dataset with its latent action.
struct Pairs {
  std::vector<torch::Tensor> frames;               // per episode [T, h, w, 3] uint8 at the model's size
  std::vector<std::pair<int64_t, int64_t>> index;  // (episode, t) per row
  torch::Tensor mu;                                // [N, latent]
};

Pairs encode_dataset(models::LatentActionModel& model, const std::filesystem::path& dir,
                     int64_t max_episodes) {
  const auto& c = model->config;
  const auto store = data::EpisodeStore::open(dir);
  int64_t n = static_cast<int64_t>(store.size());
  if (max_episodes > 0) n = std::min(n, max_episodes);
  Pairs p;
  std::vector<torch::Tensor> mus;
  for (int64_t e = 0; e < n; ++e) {
    auto f = io::resize_center_crop(store.load(static_cast<size_t>(e)).frames, c.height, c.width);
    const auto mu = models::lam_encode_episode(model, f);  // [T - 1, latent]
    for (int64_t t = 0; t < mu.size(0); ++t) p.index.emplace_back(static_cast<int64_t>(p.frames.size()), t);
    p.frames.push_back(f);
    mus.push_back(mu);
  }
  DOJO_CHECK(!p.index.empty(), "lam retrieve: " + dir.string() + " has no frame pairs");
  p.mu = torch::cat(mus);
  return p;
}

// The two frames of pair `row` side by side with a white line between: [h, 2w + 1, 3].
torch::Tensor pair_image(const Pairs& p, int64_t row) {
  const auto [e, t] = p.index[static_cast<size_t>(row)];
  const auto& f = p.frames[static_cast<size_t>(e)];
  auto gap = torch::full({f.size(1), 1, 3}, 255, torch::kByte);
  return torch::cat({f[t], gap, f[t + 1]}, 1);
}

}  // namespace

torch::Tensor lam_retrieval_grid(models::LatentActionModel& model, const std::filesystem::path& query,
                                 const std::vector<std::filesystem::path>& search,
                                 const LamRetrievalOptions& o) {
  DOJO_CHECK(o.queries > 0 && o.k > 0, "lam retrieve: --queries and --k must be positive");
  const int64_t height = model->config.height, pad = 4;
  const auto q = encode_dataset(model, query, o.max_episodes);
  std::vector<Pairs> db;
  for (const auto& d : search) db.push_back(encode_dataset(model, d, o.max_episodes));
  std::vector<torch::Tensor> rows;
  const int64_t nq = std::min<int64_t>(o.queries, static_cast<int64_t>(q.index.size()));
  for (int64_t i = 0; i < nq; ++i) {
    const int64_t qi = i * static_cast<int64_t>(q.index.size()) / nq;
    std::vector<torch::Tensor> cells{pair_image(q, qi)};
    std::vector<std::tuple<double, size_t, int64_t>> candidates;  // (distance, dataset, row)
    for (size_t d = 0; d < db.size(); ++d) {
      const auto dist = (db[d].mu - q.mu[qi]).pow(2).sum(1);
      const auto kk = std::min<int64_t>(o.k, dist.size(0));
      const auto top = std::get<1>(dist.topk(kk, 0, /*largest=*/false));
      for (int64_t j = 0; j < kk; ++j) {
        const auto r = top[j].item<int64_t>();
        candidates.emplace_back(dist[r].item<double>(), d, r);
      }
    }
    std::sort(candidates.begin(), candidates.end());
    for (int64_t j = 0; j < std::min<int64_t>(o.k, static_cast<int64_t>(candidates.size())); ++j) {
      cells.push_back(torch::zeros({height, pad * 2, 3}, torch::kByte));
      cells.push_back(pair_image(db[std::get<1>(candidates[j])], std::get<2>(candidates[j])));
    }
    rows.push_back(torch::cat(cells, 1));
    rows.push_back(torch::zeros({pad, rows.back().size(1), 3}, torch::kByte));
  }
  rows.pop_back();
  return torch::cat(rows, 0).contiguous();  // [H', W', 3]
}

}  // namespace dojo::eval
