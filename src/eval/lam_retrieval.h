// Latent-action retrieval: for query frame pairs of one dataset, the frame pairs of other datasets
// whose latent actions are nearest. A picture of what the LAM treats as "the same action" across
// embodiments (the paper's cross-embodiment retrieval figure).
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <vector>

#include "models/lam.h"

namespace dojo::eval {

struct LamRetrievalOptions {
  int64_t queries = 4;       // query pairs, evenly spaced over the query dataset
  int64_t k = 3;             // neighbours per query, over all searched datasets together
  int64_t max_episodes = 0;  // per dataset; 0: all
};

// An image grid [H', W', 3] uint8: one row per query pair (its two frames side by side), followed
// by its k nearest pairs (Euclidean distance of z_mu). Throws dojo::Error naming a dataset that
// has no frame pairs.
torch::Tensor lam_retrieval_grid(models::LatentActionModel& model, const std::filesystem::path& query,
                                 const std::vector<std::filesystem::path>& search,
                                 const LamRetrievalOptions& options);

}  // namespace dojo::eval
