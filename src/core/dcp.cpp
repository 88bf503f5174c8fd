#include "core/dcp.h"

#include <torch/torch.h>

#include <fstream>
#include <sstream>

#include "core/error.h"
#include "core/pickle.h"

namespace dojo {
namespace {

namespace fs = std::filesystem;
using Kind = PickleValue::Kind;
const std::string kMeta = "torch.distributed.checkpoint.metadata.";

// A dataclass field: BUILD's state is the instance dict, or (dict, slots) for slotted classes.
const PickleValue* field(const PickleValue& object, const std::string& name) {
  if (const PickleValue* hit = object.get(name)) return hit;
  const PickleValue* state = object.state.get();
  if (!state) return nullptr;
  if (state->kind == Kind::kDict) return state->get(name);
  if (state->kind == Kind::kTuple)
    for (const auto& part : state->items)
      if (part && part->kind == Kind::kDict)
        if (const PickleValue* hit = part->get(name)) return hit;
  return nullptr;
}

class MetadataReader {
 public:
  explicit MetadataReader(std::string source) : source_(std::move(source)) {}

  Error error(const std::string& message) const { return Error(source_ + ": " + message); }

  const PickleValue& need(const PickleValue& object, const std::string& name,
                          const std::string& where) const {
    const PickleValue* value = field(object, name);
    if (!value) throw error(where + " has no field '" + name + "'");
    return *value;
  }
  const PickleValue& object_of(const PickleValue& value, const std::string& type,
                               const std::string& where) const {
    if (value.kind != Kind::kObject || value.text != type)
      throw error(where + " is a " + value.describe() + ", not a " + type);
    return value;
  }
  int64_t integer(const PickleValue& value, const std::string& where) const {
    if (value.kind != Kind::kInt) throw error(where + " is a " + value.describe() + ", not an int");
    return value.integer;
  }
  std::vector<int64_t> ints(const PickleValue& value, const std::string& where) const {
    if (value.kind != Kind::kTuple && value.kind != Kind::kList)
      throw error(where + " is a " + value.describe() + ", not a tuple");
    std::vector<int64_t> out;
    for (const auto& item : value.items) out.push_back(integer(*item, where));
    return out;
  }
  std::string text(const PickleValue& value, const std::string& where) const {
    if (!value.is_string()) throw error(where + " is a " + value.describe() + ", not a string");
    return value.text;
  }
  torch::ScalarType dtype(const PickleValue& properties, const std::string& where) const {
    // PyTorch 2.x pickles TensorProperties as the tuple (dtype, layout, requires_grad,
    // memory_format, pin_memory); earlier versions as a dict with 'dtype'.
    const PickleValue* dtype = nullptr;
    if (properties.state && properties.state->kind == Kind::kTuple && !properties.state->items.empty())
      dtype = properties.state->items[0].get();
    else
      dtype = field(properties, "dtype");
    if (!dtype || dtype->kind != Kind::kGlobal) throw error(where + ": no dtype in its properties");
    try {
      return pickled_scalar_type(dtype->text);
    } catch (const Error& e) {
      throw error(where + ": " + e.what());
    }
  }

 private:
  std::string source_;
};

std::string chunk_key(const std::string& name, const std::vector<int64_t>& offsets) {
  std::string key = name + "@";
  for (const int64_t o : offsets) key += std::to_string(o) + ",";
  return key;
}

bool boxes_overlap(const DcpChunk& a, const DcpChunk& b) {
  for (size_t d = 0; d < a.offsets.size(); ++d)
    if (a.offsets[d] >= b.offsets[d] + b.sizes[d] || b.offsets[d] >= a.offsets[d] + a.sizes[d]) return false;
  return true;
}

}  // namespace

fs::path DcpCheckpoint::resolve(const fs::path& path) {
  if (fs::is_regular_file(path / ".metadata")) return path;
  if (fs::is_regular_file(path / "model" / ".metadata")) return path / "model";
  const fs::path latest = path / "latest_checkpoint.txt";
  if (fs::is_regular_file(latest)) {
    std::ifstream in(latest);
    std::string name;
    std::getline(in, name);
    while (!name.empty() && std::isspace(static_cast<unsigned char>(name.back()))) name.pop_back();
    if (name.size() > 3 && name.compare(name.size() - 3, 3, ".pt") == 0) name.resize(name.size() - 3);
    DOJO_CHECK(!name.empty() && name.find('/') == std::string::npos && name != "..",
               latest.string() + ": does not name an iteration folder");
    const fs::path model = path / name / "model";
    DOJO_CHECK(fs::is_regular_file(model / ".metadata"), latest.string() + ": names '" + name + "', but " +
                                                             (model / ".metadata").string() + " is missing");
    return model;
  }
  throw Error(path.string() +
              ": not a distributed checkpoint (no .metadata, model/.metadata or latest_checkpoint.txt)");
}

bool DcpCheckpoint::is_dcp(const fs::path& path) {
  return fs::is_directory(path) &&
         (fs::is_regular_file(path / ".metadata") || fs::is_regular_file(path / "model" / ".metadata") ||
          fs::is_regular_file(path / "latest_checkpoint.txt"));
}

DcpCheckpoint DcpCheckpoint::open(const fs::path& path, const TorchFileOptions& options) {
  DcpCheckpoint out;
  out.dir_ = resolve(path);
  out.options_ = options;
  const fs::path meta_path = out.dir_ / ".metadata";
  const std::string source = meta_path.string();
  const auto meta_file = MappedFile::open(meta_path);
  PickleOptions pickle;
  pickle.source = source;
  pickle.allowed_globals = dcp_metadata_globals();
  for (const auto& name : options.extra_globals) pickle.allowed_globals.insert(name);
  const PickleRef root = read_pickle(meta_file->bytes(), meta_file->size, 0, pickle).value;
  const MetadataReader in(source);

  const PickleValue& metadata = in.object_of(*root, kMeta + "Metadata", "the metadata");
  // Where each chunk's bytes are: MetadataIndex(fqn, offset, index) -> _StorageInfo.
  std::map<std::string, const PickleValue*> storage;
  const PickleValue& storage_data = in.need(metadata, "storage_data", "the metadata");
  if (storage_data.kind != Kind::kDict) throw in.error("storage_data is a " + storage_data.describe());
  for (const auto& [index, info] : storage_data.entries) {
    const PickleValue& idx = in.object_of(*index, kMeta + "MetadataIndex", "a storage_data key");
    const std::string fqn = in.text(in.need(idx, "fqn", "a MetadataIndex"), "a MetadataIndex's fqn");
    const PickleValue* offset = field(idx, "offset");
    const auto offsets = offset && offset->kind != Kind::kNone ? in.ints(*offset, "a MetadataIndex's offset")
                                                               : std::vector<int64_t>{};
    storage[chunk_key(fqn, offsets)] = &in.object_of(
        *info, "torch.distributed.checkpoint.filesystem._StorageInfo", "storage of '" + fqn + "'");
  }

  const PickleValue& entries = in.need(metadata, "state_dict_metadata", "the metadata");
  if (entries.kind != Kind::kDict) throw in.error("state_dict_metadata is a " + entries.describe());
  for (const auto& [key, value] : entries.entries) {
    const std::string name = in.text(*key, "a state_dict_metadata key");
    if (value->kind == Kind::kObject && value->text == kMeta + "BytesStorageMetadata") {
      out.other_keys_.push_back(name);
      continue;
    }
    const std::string where = "tensor '" + name + "'";
    const PickleValue& meta = in.object_of(*value, kMeta + "TensorStorageMetadata", where);
    DcpTensor tensor;
    tensor.name = name;
    tensor.dtype = in.dtype(in.need(meta, "properties", where), where);
    tensor.shape = in.ints(in.need(meta, "size", where), where + "'s size");
    for (const int64_t d : tensor.shape)
      if (d < 0) throw in.error(where + " has a negative size");
    const PickleValue& chunks = in.need(meta, "chunks", where);
    if (chunks.kind != Kind::kList) throw in.error(where + "'s chunks are a " + chunks.describe());
    __int128 covered = 0;
    for (const auto& chunk_value : chunks.items) {
      const PickleValue& chunk =
          in.object_of(*chunk_value, kMeta + "ChunkStorageMetadata", where + "'s chunk");
      DcpChunk c;
      c.offsets = in.ints(in.need(chunk, "offsets", where), where + "'s chunk offsets");
      c.sizes = in.ints(in.need(chunk, "sizes", where), where + "'s chunk sizes");
      if (c.offsets.size() != tensor.shape.size() || c.sizes.size() != tensor.shape.size())
        throw in.error(where + " has a chunk of another rank than the tensor");
      __int128 numel = 1;
      for (size_t d = 0; d < c.sizes.size(); ++d) {
        if (c.offsets[d] < 0 || c.sizes[d] < 0 || c.offsets[d] + c.sizes[d] > tensor.shape[d])
          throw in.error(where + " has a chunk outside the tensor");
        numel *= c.sizes[d];
      }
      covered += numel;
      const auto it = storage.find(chunk_key(name, c.offsets));
      if (it == storage.end()) throw in.error(where + " has a chunk with no storage entry");
      const PickleValue& info = *it->second;
      c.file = in.text(in.need(info, "relative_path", where), where + "'s file");
      if (c.file.empty() || c.file.find('/') != std::string::npos || c.file == "." || c.file == "..")
        throw in.error(where + " names the file '" + c.file + "' (not a file of this folder)");
      const int64_t byte_offset = in.integer(in.need(info, "offset", where), where + "'s byte offset");
      const int64_t length = in.integer(in.need(info, "length", where), where + "'s byte length");
      if (byte_offset < 0 || length < 0) throw in.error(where + " has a negative byte range");
      c.byte_offset = static_cast<uint64_t>(byte_offset);
      c.length = static_cast<uint64_t>(length);
      if (const PickleValue* transforms = field(info, "transform_descriptors"))
        if (!transforms->items.empty())
          throw in.error(where +
                         " is stored with transforms (compression?), which this reader does not undo");
      tensor.chunks.push_back(std::move(c));
    }
    __int128 numel = 1;
    for (const int64_t d : tensor.shape) numel *= d;
    for (size_t i = 0; i < tensor.chunks.size(); ++i)
      for (size_t j = 0; j < i; ++j)
        if (boxes_overlap(tensor.chunks[i], tensor.chunks[j]))
          throw in.error(where + " has overlapping chunks");
    if (covered != numel) throw in.error(where + "'s chunks do not cover it exactly");
    out.tensors_.push_back(std::move(tensor));
  }
  return out;
}

const DcpTensor* DcpCheckpoint::find(const std::string& name) const {
  for (const auto& t : tensors_)
    if (t.name == name) return &t;
  return nullptr;
}

torch::Tensor DcpCheckpoint::tensor(const DcpTensor& entry) const {
  torch::Tensor out = torch::empty(entry.shape, torch::TensorOptions().dtype(entry.dtype));
  for (const auto& chunk : entry.chunks) {
    auto& file = files_[chunk.file];
    if (!file) file = MappedFile::open(dir_ / chunk.file);
    const std::string source = (dir_ / chunk.file).string() + " (bytes " + std::to_string(chunk.byte_offset) +
                               "+" + std::to_string(chunk.length) + ", '" + entry.name + "')";
    if (chunk.byte_offset > file->size || chunk.length > file->size - chunk.byte_offset)
      throw Error(source + ": runs past the end of the file (" + std::to_string(file->size) + " bytes)");
    const TorchFile archive =
        TorchFile::from_archive(file, file->bytes() + chunk.byte_offset, chunk.length, source, options_);
    if (!TorchFile::is_tensor(archive.root())) throw Error(source + ": holds a " + archive.root().describe());
    const torch::Tensor part = archive.tensor(archive.root());
    if (part.sizes().vec() != chunk.sizes || part.scalar_type() != entry.dtype)
      throw Error(source + ": holds " + std::string(c10::toString(part.scalar_type())) + " " +
                  shape_string(part.sizes()) + ", the metadata says " + c10::toString(entry.dtype) + " " +
                  shape_string(chunk.sizes));
    torch::Tensor target = out;
    for (size_t d = 0; d < chunk.offsets.size(); ++d)
      target = target.narrow(static_cast<int64_t>(d), chunk.offsets[d], chunk.sizes[d]);
    target.copy_(part);
  }
  return out;
}

}  // namespace dojo
