// A hash of text that is the same on every build and platform, for seeds and placements that must
// reproduce (std::hash may differ between standard libraries).
#pragma once

#include <cstdint>
#include <string_view>

namespace dojo {

// FNV-1a, then the splitmix64 finaliser: every output bit depends on every input byte (FNV-1a's
// low bit alone is only the parity of the bytes).
inline uint64_t stable_hash(std::string_view text) {
  uint64_t h = 1469598103934665603ull;
  for (const unsigned char c : text) h = (h ^ c) * 1099511628211ull;
  h = (h ^ (h >> 30)) * 0xbf58476d1ce4e5b9ull;
  h = (h ^ (h >> 27)) * 0x94d049bb133111ebull;
  return h ^ (h >> 31);
}

}  // namespace dojo
