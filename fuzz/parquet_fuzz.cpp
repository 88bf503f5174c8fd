// libFuzzer target for the Parquet reader: any input must either decode or throw dojo::Error;
// a crash, a sanitizer report, an uncaught exception or an out-of-memory is a bug.
// Build and run with scripts/fuzz_parquet.sh (clang, -fsanitize=fuzzer,address,undefined).
#include <cstdint>
#include <string>

#include "core/error.h"
#include "io/parquet.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  dojo::io::ParquetLimits limits;  // small caps: the fuzzer runs with a 2 GB RSS limit
  limits.max_file_bytes = 1 << 24;
  limits.max_page_bytes = 1 << 22;
  limits.max_column_values = 1 << 20;
  try {
    const auto file = dojo::io::ParquetFile::from_buffer(
        std::string(reinterpret_cast<const char*>(data), size), "fuzz", limits);
    for (const auto& column : file.columns()) {
      // Every typed reader on every column: wrong types must be refused cleanly too.
      try {
        (void)file.read_i64(column.name);
      } catch (const dojo::Error&) {
      }
      try {
        (void)file.read_f64(column.name);
      } catch (const dojo::Error&) {
      }
      try {
        (void)file.read_string(column.name);
      } catch (const dojo::Error&) {
      }
      try {
        (void)file.read_list_f32(column.name);
      } catch (const dojo::Error&) {
      }
      try {
        (void)file.read_list_string(column.name);
      } catch (const dojo::Error&) {
      }
    }
    (void)file.decode_all();
  } catch (const dojo::Error&) {
  }
  return 0;
}
