// How much a latent action model knows about the actions: a ridge probe from latent actions to
// the ground-truth motion between the same frames, fitted on some episodes and scored (R²) on the
// held-out rest. Robot datasets probe action deltas; human ones the hidden hand motion.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "models/lam.h"

namespace dojo::eval {

struct ProbeResult {
  double r2_train = 0, r2_heldout = 0;  // mean over target dims of 1 - SSE / SST
  std::vector<double> r2_heldout_per_dim;
  int64_t n_train = 0, n_heldout = 0;
  int64_t target_dims = 0;
};

// What moved between frames t and t+1, for pairing with the latent action of that frame pair.
// `commanded` rows (actions, and human hand commands) are issued after frame t is observed and
// executed during step t (the LeRobot convention), so the pair's motion is cmd[t] - cmd[t-1] and
// the first pair has no target. Measured rows (poses observed with frame t) give pose[t+1] - pose[t].
struct ProbePairs {
  int64_t first_pair = 0;  // latent-action rows [first_pair, first_pair + deltas.size(0)) match
  torch::Tensor deltas;    // [n, K]
};
ProbePairs probe_deltas(const torch::Tensor& rows, bool commanded);

// Ridge regression (with intercept) from x [N, D] to y [N, K], fitted on the train rows.
ProbeResult ridge_probe(const torch::Tensor& x_train, const torch::Tensor& y_train,
                        const torch::Tensor& x_test, const torch::Tensor& y_test, double lambda = 1e-3);

enum class ProbeTarget { kAuto, kAction, kMotion };       // auto: actions when present, else hidden motion
ProbeTarget parse_probe_target(const std::string& text);  // auto | action | motion

struct LamProbeOptions {
  ProbeTarget target = ProbeTarget::kAuto;
  double lambda = 1e-3;      // ridge strength, relative to the sample count
  int64_t max_episodes = 0;  // per dataset; 0: all
};

// The probe on one dataset: the first 80% of its episodes fit, the rest are held out. Returns
// {data, embodiment, target, target_dims, train_pairs, heldout_pairs, r2_train, r2_heldout,
// r2_heldout_per_dim}.
nlohmann::json probe_lam(models::LatentActionModel& model, const std::filesystem::path& dataset,
                         const LamProbeOptions& options);

}  // namespace dojo::eval
