#include "core/log.h"

#include <atomic>
#include <cstdio>
#include <mutex>

namespace dojo {
namespace {
std::atomic<int> g_level{static_cast<int>(LogLevel::kInfo)};
std::mutex g_log_mutex;
}  // namespace

void set_log_level(LogLevel level) { g_level = static_cast<int>(level); }
LogLevel log_level() { return static_cast<LogLevel>(g_level.load()); }

void log_message(LogLevel level, const std::string& message) {
  static const char* const kTags[] = {"DEBUG", "INFO ", "WARN ", "ERROR"};
  std::lock_guard<std::mutex> lock(g_log_mutex);
  std::fprintf(stderr, "[%s] %s\n", kTags[static_cast<int>(level)], message.c_str());
  std::fflush(stderr);
}

}  // namespace dojo
