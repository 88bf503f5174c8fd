// A whole file memory-mapped for reading, shared by the tensors built on it.
//
// The mapping is private and writable (copy-on-write), so a tensor made on it may be modified in
// place without touching the file, and MAP_NORESERVE so that a mapping larger than RAM + swap is
// not refused for commit accounting. Used by the safetensors, torch.save and DCP readers.
#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <memory>

namespace dojo {

struct MappedFile {
  std::filesystem::path path;
  void* base = nullptr;  // null for an empty file
  size_t size = 0;

  MappedFile() = default;
  MappedFile(const MappedFile&) = delete;
  MappedFile& operator=(const MappedFile&) = delete;
  ~MappedFile();

  const uint8_t* bytes() const { return static_cast<const uint8_t*>(base); }

  // Maps the regular file at `path`; throws dojo::Error naming it when it is missing, not a
  // regular file or cannot be mapped.
  static std::shared_ptr<const MappedFile> open(const std::filesystem::path& path);
  // Maps `size` bytes of the open descriptor `fd` (the caller keeps and closes fd).
  static std::shared_ptr<const MappedFile> map(int fd, size_t size, const std::filesystem::path& path);
};

}  // namespace dojo
