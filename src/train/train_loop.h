// The one training loop every trainer runs (LAM, tokenizer, world model; distillation next): it
// owns what is the same for all of them, so a trainer only says what one step and one save are.
//
//   resume       the loop starts at the trainer's restored step and runs up to options.steps
//   budgets      a step budget (options.steps) and an optional wall-clock budget; whichever ends
//                first makes the step in flight the last one, which is always followed by a save
//   progress     one dojo::Progress line (bar, rate, ETA under either budget)
//   loss curve   "step,<columns>" CSV rewritten atomically at every save; a resumed run drops
//                rows after its checkpoint's step, so the curve never repeats a step
//   saves        every save_every steps and after the last step
//   throughput   items per second over the steady state (the first steps warm allocators up)
//   roofline     the first steady step's matrix products are counted (core/gemm_census.h) and
//                timed alone after the run by the main process (not when the time budget ended
//                it): the log says what share of their speed the steps run at
//   rank 0       only the main process draws progress, writes the curve and saves
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

namespace dojo::train {

struct LoopOptions {
  std::string name;                  // progress label and log prefix, e.g. "lam train"
  int64_t steps = 0;                 // total steps; a resumed run continues up to this
  double time_budget_s = 0;          // wall-clock budget from the loop's start; 0: none
  int64_t save_every = 0;            // save after every N-th step (0: only after the last)
  std::filesystem::path loss_curve;  // CSV file; empty: none
  std::vector<std::string> columns;  // curve columns after "step"
  std::string unit = "clips";        // what StepRecord::items counts
  bool progress = true;              // draw a progress line (main process only)
  bool main_process = true;          // false on ranks > 0: no progress, curve or saves
  bool roofline = true;              // count one step's matrix products and time them alone
};

// What the step function is told about the step it is asked to run.
struct LoopStep {
  int64_t index = 0;           // 0-based: the steps done before this one
  bool last = false;           // no step follows (step budget reached or time budget spent)
  bool saves = false;          // a save follows this step
  double budget_fraction = 0;  // share of the time budget spent so far (0 without one)
};

// What one step reports back.
struct StepRecord {
  std::vector<double> values;  // one per LoopOptions::columns; NaN leaves the cell empty
  int64_t items = 0;           // samples trained on, for throughput
  std::string note;            // shown on the progress line, e.g. "loss 0.123"
};

struct LoopResult {
  int64_t start_step = 0, end_step = 0;
  double seconds = 0;           // wall time of the loop
  double items_per_second = 0;  // steady state: steps after the first two of this run
  bool out_of_time = false;     // the time budget ended the run
  // With LoopOptions::roofline, at least 4 steps in this run and no time budget spent: the
  // steady steps' mean time against their matrix products' time alone (main process; 0 when not
  // measured).
  int64_t products = 0;       // matrix products in the counted step
  double products_flops = 0;  // and their FLOPs
  double step_seconds = 0;
  double products_seconds_alone = 0;
  double roofline_fraction = 0;
};

// Runs step(s) for s = start_step, start_step + 1, ... until options.steps or the time budget,
// then save(steps_done, last) wherever LoopStep::saves was set. Returns at once (no save) when
// start_step >= options.steps.
LoopResult run_training_loop(const LoopOptions& options, int64_t start_step,
                             const std::function<StepRecord(const LoopStep&)>& step,
                             const std::function<void(int64_t steps_done, bool last)>& save);

}  // namespace dojo::train
