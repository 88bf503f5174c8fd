#include "core/progress.h"

#include <unistd.h>

#include <cmath>
#include <cstdio>

#include "core/log.h"

namespace dojo {

Progress::Progress(std::string label, int64_t total, std::string unit)
    : label_(std::move(label)),
      total_(total),
      unit_(std::move(unit)),
      // Below INFO (--quiet, a data-parallel rank other than 0) no bar is drawn either.
      tty_(isatty(fileno(stderr)) != 0 && log_level() <= LogLevel::kInfo),
      start_(std::chrono::steady_clock::now()),
      last_draw_(start_) {
  if (!tty_) LOG_INFO(label_, ": 0/", total_, " ", unit_);
}

Progress::~Progress() {
  // A loop left by an exception must not leave a half-drawn line behind.
  if (tty_ && !finished_ && done_ > 0) std::fprintf(stderr, "\n");
}

double Progress::elapsed_seconds() const {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
}

std::string Progress::format_duration(double seconds) {
  char buf[32];
  if (!std::isfinite(seconds) || seconds < 0) return "?";
  if (seconds < 60) {
    std::snprintf(buf, sizeof buf, "%.1fs", seconds);
  } else if (seconds < 3600) {
    const int s = static_cast<int>(seconds);
    std::snprintf(buf, sizeof buf, "%dm%02ds", s / 60, s % 60);
  } else {
    const int m = static_cast<int>(seconds / 60);
    std::snprintf(buf, sizeof buf, "%dh%02dm", m / 60, m % 60);
  }
  return buf;
}

void Progress::advance(int64_t n, const std::string& note) {
  done_ += n;
  if (!note.empty()) note_ = note;
  draw(done_ >= total_);
}

void Progress::set_note(const std::string& note) {
  note_ = note;
  draw(false);
}

void Progress::draw(bool force) {
  const auto now = std::chrono::steady_clock::now();
  const double since_draw = std::chrono::duration<double>(now - last_draw_).count();
  const double min_interval = tty_ ? 0.1 : log_every_seconds_;
  if (!force && since_draw < min_interval) return;
  last_draw_ = now;

  const double elapsed = elapsed_seconds();
  const double rate = elapsed > 0 ? done_ / elapsed : 0.0;
  char rate_text[48];
  if (rate >= 1.0 || rate == 0.0) {
    std::snprintf(rate_text, sizeof rate_text, "%.2f %s/s", rate, unit_.c_str());
  } else {
    // "s/episode" reads better than "s/episodes".
    std::string singular = unit_;
    if (singular.size() > 2 && singular.back() == 's') singular.pop_back();
    std::snprintf(rate_text, sizeof rate_text, "%.2f s/%s", 1.0 / rate, singular.c_str());
  }
  double eta = rate > 0 && total_ > 0 ? (total_ - done_) / rate : NAN;
  int64_t total = total_;
  double frac = total_ > 0 ? std::min(1.0, static_cast<double>(done_) / total_) : 0.0;
  std::string total_prefix;
  if (time_budget_s_ > 0) {
    const double left = std::max(0.0, time_budget_s_ - elapsed);
    if (std::isnan(eta) || left < eta) {
      eta = left;
      frac = std::min(1.0, elapsed / time_budget_s_);
      if (rate > 0) {
        total = std::min<int64_t>(total_, done_ + static_cast<int64_t>(left * rate));
        total_prefix = "~";
      }
    }
  }

  if (tty_) {
    constexpr int kWidth = 30;
    const int filled = static_cast<int>(frac * kWidth);
    std::string bar(kWidth, ' ');
    for (int i = 0; i < filled; ++i) bar[i] = '=';
    if (filled < kWidth) bar[filled] = '>';
    std::fprintf(stderr, "\r%s [%s] %lld/%s%lld %s ETA %s %s\033[K", label_.c_str(), bar.c_str(),
                 static_cast<long long>(done_), total_prefix.c_str(), static_cast<long long>(total),
                 rate_text, format_duration(eta).c_str(), note_.c_str());
    std::fflush(stderr);
  } else {
    LOG_INFO(label_, ": ", done_, "/", total_prefix, total, " ", unit_, ", ", rate_text, ", ETA ",
             format_duration(eta), note_.empty() ? "" : ", ", note_);
  }
}

void Progress::finish() {
  if (finished_) return;
  finished_ = true;
  const double elapsed = elapsed_seconds();
  if (tty_ && done_ > 0) std::fprintf(stderr, "\n");
  char rate[48];
  std::snprintf(rate, sizeof rate, "%.2f", elapsed > 0 ? done_ / elapsed : 0.0);
  LOG_INFO(label_, ": done ", done_, " ", unit_, " in ", format_duration(elapsed), " (", rate, " ", unit_,
           "/s)", note_.empty() ? "" : ", ", note_);
}

}  // namespace dojo
