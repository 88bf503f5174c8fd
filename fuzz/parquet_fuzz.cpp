// libFuzzer target for the Parquet reader (see parquet_replay.h for what counts as a bug).
// Build and run with scripts/fuzz_parquet.sh (clang, -fsanitize=fuzzer,address,undefined).
#include <cstdint>
#include <string>

#include "parquet_replay.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  (void)dojo::fuzz::replay_parquet_input(std::string(reinterpret_cast<const char*>(data), size));
  return 0;
}
