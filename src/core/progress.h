// Progress reporting for long loops. On a TTY: one line redrawn in place with a bar,
// done/total, rate (it/s, or s/it when slower than one per second) and ETA. Not on a TTY:
// a plain log line every `log_every_seconds`. A summary line is printed by finish().
#pragma once

#include <chrono>
#include <cstdint>
#include <string>

namespace dojo {

class Progress {
 public:
  Progress(std::string label, int64_t total, std::string unit = "it");
  ~Progress();
  Progress(const Progress&) = delete;
  Progress& operator=(const Progress&) = delete;

  // Advances by n; `note` is shown after the numbers (e.g. "loss 0.123").
  void advance(int64_t n = 1, const std::string& note = "");
  void set_note(const std::string& note);
  // A loop that also stops when `seconds` have passed since construction (a training time
  // budget): the bar and ETA follow whichever limit comes first, and the total reads "~N" as
  // the step count the budget allows at the current rate. 0 = none.
  void set_time_budget(double seconds) { time_budget_s_ = seconds; }
  // Prints the summary: "label: done N unit in T s (R unit/s)". Idempotent.
  void finish();

  int64_t done() const { return done_; }
  double elapsed_seconds() const;

  // Formats seconds as "1h02m", "3m05s" or "4.2s".
  static std::string format_duration(double seconds);

 private:
  void draw(bool force);

  std::string label_;
  int64_t total_;
  std::string unit_;
  int64_t done_ = 0;
  std::string note_;
  bool tty_;
  bool finished_ = false;
  std::chrono::steady_clock::time_point start_;
  std::chrono::steady_clock::time_point last_draw_;
  double log_every_seconds_ = 10.0;
  double time_budget_s_ = 0;
};

}  // namespace dojo
