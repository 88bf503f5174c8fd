// What the Parquet fuzzer does with one input, shared by the fuzz target and the test that
// replays the committed corpus: open it with small limits, call every typed reader on every
// column, then decode everything. Any input must either decode or throw dojo::Error; a crash, a
// sanitizer report, another exception or an out-of-memory is a bug. Returns whether the whole
// file decoded (false: it threw dojo::Error somewhere).
#pragma once

#include <cstdint>
#include <string>

#include "core/error.h"
#include "io/parquet.h"

namespace dojo::fuzz {

inline bool replay_parquet_input(const std::string& bytes) {
  io::ParquetLimits limits;  // small caps: the fuzzer runs with a 2 GB RSS limit
  limits.max_file_bytes = 1 << 24;
  limits.max_page_bytes = 1 << 22;
  limits.max_column_values = 1 << 20;
  try {
    const auto file = io::ParquetFile::from_buffer(bytes, "fuzz", limits);
    for (const auto& column : file.columns()) {
      // Every typed reader on every column: wrong types must be refused cleanly too.
      try {
        (void)file.read_i64(column.name);
      } catch (const Error&) {
      }
      try {
        (void)file.read_f64(column.name);
      } catch (const Error&) {
      }
      try {
        (void)file.read_string(column.name);
      } catch (const Error&) {
      }
      try {
        (void)file.read_list_f32(column.name);
      } catch (const Error&) {
      }
      try {
        (void)file.read_list_string(column.name);
      } catch (const Error&) {
      }
    }
    (void)file.decode_all();
    return true;
  } catch (const Error&) {
    return false;
  }
}

}  // namespace dojo::fuzz
