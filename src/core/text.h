// Small text helpers shared by the readers of users' files.
#pragma once

#include <algorithm>
#include <cctype>
#include <string>

namespace dojo {

// The ASCII letters of `s` in lower case (names and extensions compared without case).
inline std::string ascii_lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

}  // namespace dojo
