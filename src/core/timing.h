// Wall-clock intervals on the steady clock, for timings that are reported (never for logic).
#pragma once

#include <chrono>

namespace dojo {

inline double seconds_since(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

}  // namespace dojo
