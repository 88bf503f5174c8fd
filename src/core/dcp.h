// torch.distributed.checkpoint (DCP) folders, read without Python: the released DreamDojo
// checkpoints are saved this way, every tensor sharded across the ranks that wrote it.
//
// On disk (PyTorch 2.x FileSystemWriter): `.metadata`, a pickle of the checkpoint's Metadata (per
// key: dtype, global size and chunks; per chunk: the file, byte offset and length holding it), and
// one `__R_0.distcp` file per rank whose byte ranges are each a complete torch.save archive of one
// chunk. The metadata is interpreted by core/pickle.h against dcp_metadata_globals(); the chunks by
// core/torch_file.h. A tensor is reassembled from all its chunks, which must tile it exactly (no
// gap, no overlap, each the shape and dtype the metadata gives).
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <filesystem>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "core/mapped_file.h"
#include "core/torch_file.h"

namespace dojo {

struct DcpChunk {
  std::vector<int64_t> offsets;  // where the chunk starts in the global tensor
  std::vector<int64_t> sizes;    // the chunk's shape
  std::string file;              // relative path of the .distcp file holding it
  uint64_t byte_offset = 0;      // its torch.save archive: [byte_offset, byte_offset + length)
  uint64_t length = 0;
};

struct DcpTensor {
  std::string name;
  torch::ScalarType dtype = torch::kFloat;
  std::vector<int64_t> shape;
  std::vector<DcpChunk> chunks;
};

class DcpCheckpoint {
 public:
  // The folder holding `.metadata` for any of the forms a release ships: that folder itself, an
  // `iter_NNNNNNNNN` folder (its `model/`), or a `checkpoints/` folder whose
  // `latest_checkpoint.txt` names the iteration ("iter_000000010.pt" or "iter_000000010").
  // Throws dojo::Error naming what is missing.
  static std::filesystem::path resolve(const std::filesystem::path& path);
  // Whether `path` is a folder resolve() accepts.
  static bool is_dcp(const std::filesystem::path& path);

  // Reads and checks the metadata; chunks are read by tensor().
  static DcpCheckpoint open(const std::filesystem::path& path, const TorchFileOptions& options = {});

  const std::filesystem::path& dir() const { return dir_; }
  // Tensor entries in the metadata's order.
  const std::vector<DcpTensor>& tensors() const { return tensors_; }
  // Entries that are not tensors (pickled bytes such as trainer state), by name.
  const std::vector<std::string>& other_keys() const { return other_keys_; }
  const DcpTensor* find(const std::string& name) const;
  // The whole tensor, reassembled from every rank's chunks (CPU, contiguous).
  torch::Tensor tensor(const DcpTensor& entry) const;

 private:
  std::filesystem::path dir_;
  TorchFileOptions options_;
  std::vector<DcpTensor> tensors_;
  std::vector<std::string> other_keys_;
  mutable std::map<std::string, std::shared_ptr<const MappedFile>> files_;
};

}  // namespace dojo
