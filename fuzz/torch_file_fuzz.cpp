// libFuzzer target for the torch.save / pickle / ZIP readers (see torch_file_replay.h for what
// counts as a bug). Build and run with scripts/fuzz_torch_file.sh.
#include <cstdint>
#include <string>

#include "torch_file_replay.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  (void)dojo::fuzz::replay_torch_file_input(std::string(reinterpret_cast<const char*>(data), size));
  return 0;
}
