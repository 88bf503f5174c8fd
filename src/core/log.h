// Minimal leveled logging to stderr: "[INFO ] message". Quiet by default below INFO.
#pragma once

#include <sstream>
#include <string>

namespace dojo {

enum class LogLevel { kDebug = 0, kInfo = 1, kWarn = 2, kError = 3, kQuiet = 4 };

void set_log_level(LogLevel level);
LogLevel log_level();
void log_message(LogLevel level, const std::string& message);

namespace detail {
// Streams its arguments into one string; used by the macros below.
template <typename... Args>
std::string concat(const Args&... args) {
  std::ostringstream out;
  (out << ... << args);
  return out.str();
}
}  // namespace detail

}  // namespace dojo

#define DOJO_LOG(level, ...)                                              \
  do {                                                                    \
    if (static_cast<int>(level) >= static_cast<int>(::dojo::log_level())) \
      ::dojo::log_message(level, ::dojo::detail::concat(__VA_ARGS__));    \
  } while (0)
#define LOG_DEBUG(...) DOJO_LOG(::dojo::LogLevel::kDebug, __VA_ARGS__)
#define LOG_INFO(...) DOJO_LOG(::dojo::LogLevel::kInfo, __VA_ARGS__)
#define LOG_WARN(...) DOJO_LOG(::dojo::LogLevel::kWarn, __VA_ARGS__)
#define LOG_ERROR(...) DOJO_LOG(::dojo::LogLevel::kError, __VA_ARGS__)
