#include "train/train_loop.h"

#include <chrono>
#include <cmath>
#include <optional>
#include <sstream>

#include "core/gemm_census.h"
#include "core/log.h"
#include "core/progress.h"
#include "train/data_parallel.h"
#include "train/train_util.h"

namespace dojo::train {
namespace {

double seconds_between(std::chrono::steady_clock::time_point a, std::chrono::steady_clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}

std::string curve_header(const std::vector<std::string>& columns) {
  std::string header = "step";
  for (const auto& c : columns) header += "," + c;
  return header;
}

std::string curve_row(int64_t step, const std::vector<double>& values) {
  std::ostringstream row;
  row.precision(6);
  row << step;
  for (double v : values) {
    row << ',';
    if (!std::isnan(v)) row << v;
  }
  return row.str();
}

}  // namespace

LoopResult run_training_loop(const LoopOptions& o, int64_t start_step,
                             const std::function<StepRecord(const LoopStep&)>& step,
                             const std::function<void(int64_t, bool)>& save) {
  LoopResult result;
  result.start_step = result.end_step = start_step;
  if (start_step >= o.steps) return result;

  const auto start = std::chrono::steady_clock::now();
  // Under data parallelism only rank 0 draws, writes and saves; every rank runs the same steps.
  auto& group = data_parallel();
  const bool main = o.main_process && group.main();
  std::optional<LossCurve> curve;
  if (main && !o.loss_curve.empty()) curve.emplace(o.loss_curve, curve_header(o.columns), start_step);
  std::optional<Progress> progress;
  if (main && o.progress) {
    progress.emplace(o.name, o.steps - start_step, "step");
    progress->set_time_budget(o.time_budget_s);
  }
  // With a time budget the ranks share one clock (the mean of theirs), so all of them make the
  // same step the last one and no rank waits in a collective for a peer that has stopped.
  // The budget itself is agreed too: a trainer may have computed it from its own clock.
  const double budget = o.time_budget_s > 0 ? group.mean({o.time_budget_s})[0] : 0.0;
  auto elapsed = [&] {
    const double mine = seconds_between(start, std::chrono::steady_clock::now());
    return budget > 0 ? group.mean({mine})[0] : mine;
  };

  int64_t timed_items = 0, timed_steps = 0;
  double timed_seconds = 0;
  std::vector<GemmRecord> products;
  for (int64_t s = start_step; s < o.steps; ++s) {
    LoopStep info;
    info.index = s;
    const double now = elapsed();
    info.budget_fraction = budget > 0 ? std::min(1.0, now / budget) : 0.0;
    result.out_of_time = budget > 0 && now >= budget;
    info.last = s + 1 == o.steps || result.out_of_time;
    info.saves = info.last || (o.save_every > 0 && (s + 1) % o.save_every == 0);

    // The first steps of a run warm up allocators, caches and thread pools; the first steady one
    // is counted (which slows it: it stays out of the throughput) when a later one will be timed.
    const bool counted = o.roofline && s - start_step == 2 && s + 1 < o.steps;
    std::optional<GemmCensus> census;
    if (counted) census.emplace();
    const auto t0 = std::chrono::steady_clock::now();
    const StepRecord record = step(info);
    const double secs = seconds_between(t0, std::chrono::steady_clock::now());
    if (census) {
      products = census->records();
      census.reset();
    }
    if (s - start_step >= 2 && !counted) {
      timed_items += record.items;
      timed_seconds += secs;
      ++timed_steps;
    }
    if (curve) curve->add(curve_row(s + 1, record.values));
    if (progress) progress->advance(1, record.note);
    if (info.saves && main) {
      save(s + 1, info.last);
      if (curve) curve->write();
    }
    result.end_step = s + 1;
    if (info.last) break;
  }
  if (progress) progress->finish();
  if (result.out_of_time)
    LOG_INFO(o.name, ": time budget of ", o.time_budget_s, " s reached at step ", result.end_step);
  result.seconds = seconds_between(start, std::chrono::steady_clock::now());
  result.items_per_second = timed_seconds > 0 ? static_cast<double>(timed_items) / timed_seconds : 0;
  // Timed alone by the main process only (ranks sharing a machine would time each other's
  // products), and not past a time budget the run has spent.
  if (main && !result.out_of_time && !products.empty() && timed_steps > 0) {
    const auto roofline = time_alone(products, 3);
    result.products = roofline.calls;
    result.products_flops = roofline.flops;
    result.step_seconds = timed_seconds / static_cast<double>(timed_steps);
    result.products_seconds_alone = roofline.seconds_alone;
    result.roofline_fraction = roofline.fraction_of(result.step_seconds);
    LOG_INFO(o.name, ": ", describe(roofline, result.step_seconds));
  }
  return result;
}

}  // namespace dojo::train
