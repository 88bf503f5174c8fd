// `dojo bench`: a small harness that times named workloads (warm-up, then repeats) and
// reports mean ± std in a markdown table, in the spirit of llama-bench. Rows quote the
// machine's matmul roofline so later rows can state their efficiency against it.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace dojo::bench {

struct BenchOptions {
  int warmup = 1;
  int repeats = 5;
  std::string device = "cpu";
  std::vector<std::string> only;  // row names to run; empty = all
  std::string video_path;         // decode row input; empty = a generated clip
};

// One workload: runs once and returns the throughput measured for that run, in `unit`.
struct BenchCase {
  std::string name;
  std::string unit;
  std::string params;  // the knobs of this row, printed beside it
  std::function<double()> run_once;
};

struct BenchRow {
  std::string name;
  std::string unit;
  std::string params;
  double mean = 0;
  double stddev = 0;
  int repeats = 0;
};

// Runs `cases` with warm-up and repeats; progress is logged per row.
std::vector<BenchRow> run_cases(const std::vector<BenchCase>& cases, const BenchOptions& options);

// The built-in rows: matmul GFLOP/s, video decode/encode FPS, and whatever later
// subsystems register (sim render FPS, clip loader clips/s).
std::vector<BenchCase> builtin_cases(const BenchOptions& options);

// Markdown: a header naming commit, device, threads and BLAS, then one row per case.
std::string to_markdown(const std::vector<BenchRow>& rows, const BenchOptions& options);
nlohmann::json to_json(const std::vector<BenchRow>& rows, const BenchOptions& options);

// Registry for subsystems that want a row without the bench module depending on them.
void register_case_factory(std::function<std::vector<BenchCase>(const BenchOptions&)> factory);

}  // namespace dojo::bench
