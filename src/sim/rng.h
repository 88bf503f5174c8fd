// Deterministic random numbers for DojoSim. Every draw goes through an explicitly seeded Rng so a
// scene or an episode is a pure function of its seed. The distributions are written here rather
// than taken from <random> because std::uniform_real_distribution & co. are implementation-defined
// and would make datasets differ between standard libraries.
#pragma once

#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

namespace dojo::sim {

class Rng {
 public:
  explicit Rng(uint64_t seed) : engine_(seed) {}

  // Uniform in [0, 1) with 53 random bits.
  double uniform() { return static_cast<double>(engine_() >> 11) * 0x1.0p-53; }
  double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }
  // Uniform integer in [lo, hi] (inclusive); the modulo bias is negligible for small ranges.
  int randint(int lo, int hi) {
    return lo + static_cast<int>(engine_() % static_cast<uint64_t>(hi - lo + 1));
  }
  bool bernoulli(double p) { return uniform() < p; }
  // Standard normal via Box-Muller (one value per call; the pair's second value is discarded so
  // the stream position depends only on the number of calls).
  double normal(double mean = 0.0, double std = 1.0) {
    double u1 = uniform();
    double u2 = uniform();
    if (u1 < 1e-300) u1 = 1e-300;
    return mean + std * std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * M_PI * u2);
  }
  template <typename T>
  const T& pick(const std::vector<T>& items) {
    return items[static_cast<size_t>(randint(0, static_cast<int>(items.size()) - 1))];
  }
  // A new independent stream derived from this one (for sub-components that must not shift the
  // parent's sequence when they change how many numbers they draw).
  uint64_t fork_seed() { return engine_() ^ 0x9e3779b97f4a7c15ULL; }

 private:
  std::mt19937_64 engine_;
};

}  // namespace dojo::sim
