// What the checkpoint-reader fuzzer does with one input, shared by the fuzz target and the test
// that replays the committed corpus: read it as a whole torch.save file (ZIP or legacy) and
// rebuild every tensor, then as a bare pickle with the DCP metadata allow-list. Any input must
// either read or throw dojo::Error; a crash, a sanitizer report, another exception or an
// out-of-memory is a bug. Returns whether the torch.save read succeeded.
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <memory>
#include <string>

#include "core/error.h"
#include "core/pickle.h"
#include "core/torch_file.h"

namespace dojo::fuzz {

inline bool replay_torch_file_input(const std::string& bytes) {
  auto owner = std::make_shared<std::string>(bytes);
  const auto* data = reinterpret_cast<const uint8_t*>(owner->data());
  bool read = false;
  try {
    const TorchFile file = TorchFile::from_bytes(owner, data, owner->size(), "fuzz");
    for (const auto& [name, tensor] : file.tensors()) (void)tensor.sum();
    read = true;
  } catch (const Error&) {
  }
  try {
    PickleOptions options;
    options.source = "fuzz";
    options.allowed_globals = dcp_metadata_globals();
    (void)read_pickle(data, owner->size(), 0, options);
  } catch (const Error&) {
  }
  return read;
}

}  // namespace dojo::fuzz
