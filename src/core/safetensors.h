// safetensors files: our own reader (memory-mapped) and writer (atomic).
//
// Format: 8-byte little-endian u64 N, then N bytes of UTF-8 JSON header
//   {"name": {"dtype": "F32", "shape": [2, 3], "data_offsets": [begin, end]}, ...,
//    "__metadata__": {"key": "string value", ...}}
// then the raw little-endian tensor data; data_offsets are relative to the first byte after the
// header. Readers here validate everything (header length vs file size, known dtype, byte size ==
// numel * itemsize, offsets inside the data region, tensors contiguous with no holes, overlaps or
// trailing bytes) and throw dojo::Error naming the file and the tensor.
//
// The writer emits tensors in the order given (insertion order) with contiguous offsets, compact
// JSON with the tensors first and "__metadata__" last (omitted when empty), and pads the header
// with spaces so the data starts 8-byte aligned. The same input always gives the same bytes, and
// a file read and written back is byte-identical to the original when it followed these rules
// (the golden fixtures in ../shared/golden do).
//
// Dtypes: F64 F32 F16 BF16 I64 I32 I16 I8 U8 BOOL map to torch dtypes. U16 U32 U64 F8_E4M3
// F8_E5M2 are understood in headers (listed, sized, validated) but tensor() refuses them, since
// this libtorch has no such dtype.
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <utility>
#include <vector>

namespace dojo {

// Named tensors in a chosen order (a state dict).
using NamedTensors = std::vector<std::pair<std::string, torch::Tensor>>;
// String metadata, insertion-ordered (map-like: at(), find(), count(), operator[]).
using Metadata = nlohmann::ordered_map<std::string, std::string>;

struct TensorInfo {
  std::string name;
  std::string dtype;                             // safetensors name: "F32", "BF16", ...
  std::optional<torch::ScalarType> scalar_type;  // empty for dtypes libtorch lacks (U16, F8_*, ...)
  std::vector<int64_t> shape;
  uint64_t begin = 0;  // data_offsets, relative to the data region
  uint64_t end = 0;

  int64_t numel() const;
  uint64_t nbytes() const { return end - begin; }
};

// The safetensors dtype name of a torch dtype ("F32" for kFloat); throws dojo::Error for a dtype
// safetensors files here cannot hold (complex, quantised).
std::string safetensors_dtype(torch::ScalarType type);
// Formats a shape as "[2, 3]".
std::string shape_string(c10::IntArrayRef shape);

// A safetensors file opened for reading. The header is parsed and validated at open(); tensor
// data is memory-mapped (private, copy-on-write) and read lazily. Copies share the mapping.
class SafetensorsFile {
 public:
  // Throws dojo::Error naming `path` if it is missing, unreadable or malformed.
  static SafetensorsFile open(const std::filesystem::path& path);

  const std::filesystem::path& path() const;
  uint64_t file_size() const;
  uint64_t header_size() const;  // N, the JSON header length (with padding)

  // Tensor names in header order (for files written here: the order they were saved in).
  const std::vector<std::string>& keys() const;
  bool contains(const std::string& name) const;
  // Throws dojo::Error naming the file and `name` when there is no such tensor.
  const TensorInfo& info(const std::string& name) const;
  const Metadata& metadata() const;
  // Sum of numel over all tensors.
  int64_t num_elements() const;

  // The tensor on the CPU. Without `copy` it is a zero-copy view of the mapping (kept alive by
  // the tensor), unless the data is misaligned for its dtype, in which case it is copied.
  // Views are copy-on-write: writing into one never changes the file, but is seen by other
  // views of the same tensor taken from this object or its copies. Use copy=true for an
  // independent tensor.
  torch::Tensor tensor(const std::string& name, bool copy = false) const;
  // All tensors, in key order.
  NamedTensors tensors(bool copy = false) const;
  // The raw little-endian bytes of one tensor, as stored in the file.
  std::pair<const uint8_t*, size_t> raw(const std::string& name) const;

 private:
  struct State;
  explicit SafetensorsFile(std::shared_ptr<const State> state);
  std::shared_ptr<const State> state_;
};

// Tensors made one at a time while a file is written, so that a model larger than memory can be
// converted: the header is written from `specs`, then produce(i) is called in order and each
// result is dropped once its bytes are out. A produced tensor must match its spec's shape and dtype.
struct TensorSpec {
  std::string name;
  std::vector<int64_t> shape;
  torch::ScalarType dtype = torch::kFloat32;
};
struct TensorStream {
  std::vector<TensorSpec> specs;
  std::function<torch::Tensor(size_t)> produce;
};

// Writes `tensors` (any device, any layout: copied to contiguous CPU first) and `metadata` to
// `path`, atomically (see atomic_file.h). Names must be unique and non-empty and may not be
// "__metadata__". Throws dojo::Error naming the file and the offending tensor.
void save_safetensors(const std::filesystem::path& path, const NamedTensors& tensors,
                      const Metadata& metadata = {});
// The same from a stream of tensors (the file is identical to the one the tensors would give).
void save_safetensors(const std::filesystem::path& path, const TensorStream& tensors,
                      const Metadata& metadata = {});

}  // namespace dojo
