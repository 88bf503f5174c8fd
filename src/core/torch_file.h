// torch.save files (.pt, .pth, .ckpt, and each chunk of a distributed checkpoint), read without
// running anything: the ZIP format PyTorch writes since 1.6 and the legacy format before it.
//
// The file's pickle is interpreted by core/pickle.h against an allow-list, so a file that names
// any other global (os.system, builtins.eval, ...) is refused with the global named. Tensors are
// rebuilt from the rebuild-function records (_rebuild_tensor_v2, _rebuild_parameter, ...) on the
// file's memory map: storages of the supported dtypes (fp64/32/16, bf16, int64/32/16/8, uint8,
// bool), offsets, strides and storages shared between tensors are kept; a tensor is a
// copy-on-write view of the file where its storage is aligned for its dtype, a copy otherwise.
// Only the tensors asked for are rebuilt: a Lightning checkpoint's optimizer state is parsed
// (it is part of the pickle) but never materialised.
#pragma once

#include <torch/types.h>

#include <filesystem>
#include <memory>
#include <string>
#include <unordered_map>
#include <vector>

#include "core/mapped_file.h"
#include "core/pickle.h"
#include "core/safetensors.h"

namespace dojo {

struct TorchFileOptions {
  // Dotted global names to accept beyond torch_file_globals() (as inert records: nothing is ever
  // called), for checkpoints that pickle their own hyper-parameter classes.
  std::vector<std::string> extra_globals;
};

class TorchFile {
 public:
  // Throws dojo::Error naming the file for a missing, truncated, malformed or refused file.
  static TorchFile open(const std::filesystem::path& path, const TorchFileOptions& options = {});
  // The torch.save ZIP archive in bytes [data, data + size) of `file` (a DCP chunk); `source`
  // names it in errors.
  static TorchFile from_archive(std::shared_ptr<const void> owner, const uint8_t* data, uint64_t size,
                                const std::string& source, const TorchFileOptions& options = {});
  // A whole torch.save file (ZIP or legacy) in bytes [data, data + size) that `owner` keeps alive.
  static TorchFile from_bytes(std::shared_ptr<const void> owner, const uint8_t* data, uint64_t size,
                              const std::string& source, const TorchFileOptions& options = {});

  const std::string& source() const { return source_; }
  const std::string& format() const { return format_; }  // "zip" or "legacy"
  const PickleValue& root() const { return *root_; }

  // The value at a dotted `path` below the root ("" = the root; "state_dict"; "model.ema"); a key
  // that itself contains dots is matched whole. Throws naming the path when there is none.
  const PickleValue& at(const std::string& path) const;
  // Every tensor reachable from the value at `path` through dicts, lists, tuples and container
  // objects, named by its path below it joined with '.', in the file's order.
  NamedTensors tensors(const std::string& path = "") const;
  // Whether `value` is a tensor record, and the tensor it describes.
  static bool is_tensor(const PickleValue& value);
  torch::Tensor tensor(const PickleValue& value) const;

 private:
  struct Storage {
    const uint8_t* data = nullptr;
    uint64_t nbytes = 0;
  };
  torch::Tensor rebuild(const PickleValue& storage_id, int64_t offset, const PickleValue& size,
                        const PickleValue& stride) const;

  std::string source_;
  std::string format_;
  std::shared_ptr<const void> owner_;  // the bytes tensors are views of (a memory map)
  PickleRef root_;
  std::unordered_map<std::string, Storage> storages_;
  // Each storage as one tensor, made on first use, so that every view of it shares it (also when
  // a misaligned storage had to be copied).
  mutable std::unordered_map<std::string, torch::Tensor> storage_tensors_;
};

// The torch dtype of a storage type name ("torch.BFloat16Storage"); throws for an unknown one.
torch::ScalarType storage_scalar_type(const std::string& storage_type);
// The torch dtype a pickled dtype global names ("torch.float32"); throws for an unknown one.
torch::ScalarType pickled_scalar_type(const std::string& dtype_global);

}  // namespace dojo
