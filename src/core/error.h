// Errors that reach the user. Every failure the user can cause (bad file, bad field, bad flag)
// is thrown as dojo::Error with a one-line message naming what was wrong and where; the CLI
// prints it and exits non-zero.
#pragma once

#include <stdexcept>
#include <string>

namespace dojo {

class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& message) : std::runtime_error(message) {}
};

// Bad command-line usage: the CLI exits with status 2 instead of 1.
class UsageError : public Error {
 public:
  explicit UsageError(const std::string& message) : Error(message) {}
};

}  // namespace dojo

// Throws dojo::Error(message) when cond is false. message may use operator+ on strings.
#define DOJO_CHECK(cond, message)              \
  do {                                         \
    if (!(cond)) throw ::dojo::Error(message); \
  } while (0)
