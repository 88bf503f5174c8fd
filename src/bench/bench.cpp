#include "bench/bench.h"

#include <torch/torch.h>

#include <chrono>
#include <cmath>
#include <ctime>
#include <nlohmann/json.hpp>
#include <sstream>

#include "core/log.h"
#include "core/runtime.h"

namespace dojo::bench {
namespace {

std::vector<std::function<std::vector<BenchCase>(const BenchOptions&)>>& factories() {
  static std::vector<std::function<std::vector<BenchCase>(const BenchOptions&)>> list;
  return list;
}

// Square fp32 matmul: the CPU's practical roofline for everything built from GEMMs.
BenchCase matmul_case(int64_t n, torch::Device device) {
  BenchCase c;
  c.name = "matmul_f32";
  c.unit = "GFLOP/s";
  c.params = std::to_string(n) + "x" + std::to_string(n) + "x" + std::to_string(n);
  c.run_once = [n, device] {
    torch::NoGradGuard no_grad;
    const auto a = torch::randn({n, n}, torch::TensorOptions().device(device));  // [n, n]
    const auto b = torch::randn({n, n}, torch::TensorOptions().device(device));  // [n, n]
    // Enough multiplies that one run lasts ~0.5 s on a laptop core.
    const int iters = std::max<int>(1, static_cast<int>(2e9 / (2.0 * n * n * n)));
    if (device.is_cuda()) torch::cuda::synchronize();
    const auto start = std::chrono::steady_clock::now();
    for (int i = 0; i < iters; ++i) (void)torch::mm(a, b);
    if (device.is_cuda()) torch::cuda::synchronize();
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return 2.0 * n * n * n * iters / seconds / 1e9;
  };
  return c;
}

}  // namespace

void register_case_factory(std::function<std::vector<BenchCase>(const BenchOptions&)> factory) {
  factories().push_back(std::move(factory));
}

std::vector<BenchCase> builtin_cases(const BenchOptions& options) {
  const torch::Device device = parse_device(options.device);
  std::vector<BenchCase> cases;
  cases.push_back(matmul_case(1024, device));
  for (const auto& factory : factories()) {
    auto more = factory(options);
    cases.insert(cases.end(), more.begin(), more.end());
  }
  if (options.only.empty()) return cases;
  std::vector<BenchCase> selected;
  for (auto& c : cases)
    for (const auto& name : options.only)
      if (c.name == name) selected.push_back(c);
  return selected;
}

std::vector<BenchRow> run_cases(const std::vector<BenchCase>& cases, const BenchOptions& options) {
  std::vector<BenchRow> rows;
  for (const auto& c : cases) {
    LOG_INFO("bench ", c.name, " (", c.params, "): ", options.warmup, " warm-up + ", options.repeats,
             " repeats");
    for (int i = 0; i < options.warmup; ++i) (void)c.run_once();
    std::vector<double> values;
    for (int i = 0; i < std::max(1, options.repeats); ++i) values.push_back(c.run_once());
    double mean = 0;
    for (double v : values) mean += v;
    mean /= values.size();
    double var = 0;
    for (double v : values) var += (v - mean) * (v - mean);
    // Sample standard deviation; zero for a single repeat.
    const double stddev = values.size() > 1 ? std::sqrt(var / (values.size() - 1)) : 0.0;
    rows.push_back({c.name, c.unit, c.params, mean, stddev, static_cast<int>(values.size())});
  }
  return rows;
}

std::string to_markdown(const std::vector<BenchRow>& rows, const BenchOptions& options) {
  std::ostringstream out;
  const std::time_t now = std::time(nullptr);
  char date[32];
  std::strftime(date, sizeof date, "%Y-%m-%d", std::gmtime(&now));
  out << "commit " << git_commit() << ", " << date << ", device " << options.device << ", threads "
      << threads() << ", BLAS " << blas_library() << ", torch " << torch_version() << "\n\n";
  out << "| benchmark | params | value | unit | repeats |\n|---|---|---|---|---|\n";
  for (const auto& row : rows) {
    char value[64];
    std::snprintf(value, sizeof value, "%.2f ± %.2f", row.mean, row.stddev);
    out << "| " << row.name << " | " << row.params << " | " << value << " | " << row.unit << " | "
        << row.repeats << " |\n";
  }
  return out.str();
}

nlohmann::json to_json(const std::vector<BenchRow>& rows, const BenchOptions& options) {
  nlohmann::json j;
  j["commit"] = git_commit();
  j["device"] = options.device;
  j["threads"] = threads();
  j["blas"] = blas_library();
  j["torch_version"] = torch_version();
  j["rows"] = nlohmann::json::array();
  for (const auto& row : rows)
    j["rows"].push_back({{"name", row.name},
                         {"params", row.params},
                         {"mean", row.mean},
                         {"std", row.stddev},
                         {"unit", row.unit},
                         {"repeats", row.repeats}});
  return j;
}

}  // namespace dojo::bench
