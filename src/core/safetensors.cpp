#include "core/safetensors.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <unordered_map>
#include <unordered_set>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/mapped_file.h"

static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__,
              "safetensors data is little-endian; this code copies it as host memory");

namespace dojo {
namespace {

// The Python implementation's cap; a larger header is almost surely a corrupt length field.
constexpr uint64_t kMaxHeaderSize = 100'000'000;

struct DtypeSpec {
  const char* name;
  size_t itemsize;
  std::optional<torch::ScalarType> type;
};

const std::vector<DtypeSpec>& dtype_table() {
  static const std::vector<DtypeSpec> table = {
      {"F64", 8, torch::kFloat64},   {"F32", 4, torch::kFloat32},  {"F16", 2, torch::kFloat16},
      {"BF16", 2, torch::kBFloat16}, {"I64", 8, torch::kInt64},    {"I32", 4, torch::kInt32},
      {"I16", 2, torch::kInt16},     {"I8", 1, torch::kInt8},      {"U8", 1, torch::kUInt8},
      {"BOOL", 1, torch::kBool},     {"U16", 2, std::nullopt},     {"U32", 4, std::nullopt},
      {"U64", 8, std::nullopt},      {"F8_E4M3", 1, std::nullopt}, {"F8_E5M2", 1, std::nullopt},
  };
  return table;
}

const DtypeSpec* find_dtype(const std::string& name) {
  for (const auto& spec : dtype_table())
    if (name == spec.name) return &spec;
  return nullptr;
}

std::string quote_name(const std::string& name) { return "'" + name + "'"; }

// Reads exactly `size` bytes at `offset`; false on a short read.
bool read_at(int fd, void* buffer, size_t size, uint64_t offset) {
  auto* out = static_cast<char*>(buffer);
  while (size > 0) {
    const ssize_t n = ::pread(fd, out, size, static_cast<off_t>(offset));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return false;
    out += n;
    size -= static_cast<size_t>(n);
    offset += static_cast<uint64_t>(n);
  }
  return true;
}

}  // namespace

int64_t TensorInfo::numel() const {
  int64_t n = 1;
  for (const int64_t d : shape) n *= d;
  return n;
}

std::string safetensors_dtype(torch::ScalarType type) {
  for (const auto& spec : dtype_table())
    if (spec.type && *spec.type == type) return spec.name;
  throw Error(std::string("dtype ") + c10::toString(type) + " cannot be stored in safetensors");
}

std::string shape_string(c10::IntArrayRef shape) {
  std::string text = "[";
  for (size_t i = 0; i < shape.size(); ++i) text += (i ? ", " : "") + std::to_string(shape[i]);
  return text + "]";
}

struct SafetensorsFile::State {
  std::filesystem::path path;
  uint64_t file_size = 0;
  uint64_t header_size = 0;
  std::vector<std::string> keys;
  std::unordered_map<std::string, TensorInfo> infos;
  Metadata metadata;
  std::shared_ptr<const MappedFile> mapping;  // null when the data region is empty

  const uint8_t* data(const TensorInfo& info) const {
    return static_cast<const uint8_t*>(mapping->base) + 8 + header_size + info.begin;
  }
};

SafetensorsFile::SafetensorsFile(std::shared_ptr<const State> state) : state_(std::move(state)) {}

SafetensorsFile SafetensorsFile::open(const std::filesystem::path& path) {
  const std::string file = path.string();
  auto fail = [&file](const std::string& message) -> Error { return Error(file + ": " + message); };

  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) throw fail(std::strerror(errno));
  struct FdCloser {
    int fd;
    ~FdCloser() { ::close(fd); }
  } closer{fd};

  struct stat st {};
  if (::fstat(fd, &st) != 0) throw fail(std::strerror(errno));
  if (!S_ISREG(st.st_mode)) throw fail("not a regular file");
  auto state = std::make_shared<State>();
  state->path = path;
  state->file_size = static_cast<uint64_t>(st.st_size);

  // Header length, then header.
  if (state->file_size < 8)
    throw fail("too short for a safetensors file (" + std::to_string(st.st_size) + " bytes)");
  uint8_t length_bytes[8];
  if (!read_at(fd, length_bytes, 8, 0)) throw fail("cannot read the header length");
  uint64_t n = 0;
  for (int i = 7; i >= 0; --i) n = (n << 8) | length_bytes[i];
  if (n < 2 || n > kMaxHeaderSize || n > state->file_size - 8)
    throw fail("bad header length " + std::to_string(n) + " for a file of " +
               std::to_string(state->file_size) + " bytes (not a safetensors file, or truncated)");
  state->header_size = n;
  std::string header_text(n, '\0');
  if (!read_at(fd, header_text.data(), n, 8)) throw fail("cannot read the header");
  if (header_text[0] != '{') throw fail("header does not start with '{' (not a safetensors file)");

  nlohmann::ordered_json header;
  try {
    header = nlohmann::ordered_json::parse(header_text);
  } catch (const nlohmann::json::exception& e) {
    throw fail(std::string("header is not valid JSON: ") + e.what());
  }
  if (!header.is_object()) throw fail("header is not a JSON object");

  const uint64_t data_size = state->file_size - 8 - n;
  for (const auto& [name, entry] : header.items()) {
    if (name == "__metadata__") {
      if (!entry.is_object()) throw fail("__metadata__ is not an object");
      for (const auto& [key, value] : entry.items()) {
        if (!value.is_string()) throw fail("__metadata__ value " + quote_name(key) + " is not a string");
        state->metadata[key] = value.get<std::string>();
      }
      continue;
    }
    auto bad = [&](const std::string& message) {
      return fail("tensor " + quote_name(name) + ": " + message);
    };
    if (name.empty()) throw fail("empty tensor name");
    if (!entry.is_object()) throw bad("entry is not an object");
    if (!entry.contains("dtype") || !entry["dtype"].is_string()) throw bad("missing dtype");
    if (!entry.contains("shape") || !entry["shape"].is_array()) throw bad("missing shape");
    if (!entry.contains("data_offsets") || !entry["data_offsets"].is_array() ||
        entry["data_offsets"].size() != 2)
      throw bad("missing data_offsets [begin, end]");

    TensorInfo info;
    info.name = name;
    info.dtype = entry["dtype"].get<std::string>();
    const DtypeSpec* spec = find_dtype(info.dtype);
    if (spec == nullptr) throw bad("unknown dtype " + quote_name(info.dtype));
    info.scalar_type = spec->type;

    uint64_t numel = 1;
    for (const auto& dim : entry["shape"]) {
      if (!dim.is_number_unsigned()) throw bad("shape " + entry["shape"].dump() + " is not a list of sizes");
      const uint64_t d = dim.get<uint64_t>();
      if (d > static_cast<uint64_t>(INT64_MAX) || __builtin_mul_overflow(numel, d, &numel))
        throw bad("shape " + entry["shape"].dump() + " is too large");
      info.shape.push_back(static_cast<int64_t>(d));
    }
    for (const auto& offset : entry["data_offsets"])
      if (!offset.is_number_unsigned())
        throw bad("data_offsets " + entry["data_offsets"].dump() + " are not byte offsets");
    info.begin = entry["data_offsets"][0].get<uint64_t>();
    info.end = entry["data_offsets"][1].get<uint64_t>();
    const std::string offsets =
        "data_offsets [" + std::to_string(info.begin) + ", " + std::to_string(info.end) + "]";
    if (info.end < info.begin) throw bad(offsets + " end before begin");
    if (info.end > data_size)
      throw bad(offsets + " beyond the end of the data (" + std::to_string(data_size) +
                " bytes; file truncated?)");
    uint64_t expected = 0;
    if (__builtin_mul_overflow(numel, static_cast<uint64_t>(spec->itemsize), &expected) ||
        expected != info.nbytes())
      throw bad(offsets + " hold " + std::to_string(info.nbytes()) + " bytes but " + info.dtype + " " +
                shape_string(info.shape) + " needs " + std::to_string(numel) + " x " +
                std::to_string(spec->itemsize));
    state->keys.push_back(name);
    state->infos.emplace(name, std::move(info));
  }

  // The tensors must tile the data region exactly: no overlaps, holes or trailing bytes.
  std::vector<const TensorInfo*> by_offset;
  for (const auto& key : state->keys) by_offset.push_back(&state->infos.at(key));
  std::stable_sort(by_offset.begin(), by_offset.end(),
                   [](const TensorInfo* a, const TensorInfo* b) { return a->begin < b->begin; });
  uint64_t position = 0;
  for (size_t i = 0; i < by_offset.size(); ++i) {
    const TensorInfo& info = *by_offset[i];
    if (info.begin < position)
      throw fail("tensor " + quote_name(info.name) + " overlaps tensor " +
                 quote_name(by_offset[i - 1]->name));
    if (info.begin > position)
      throw fail("tensor " + quote_name(info.name) + " starts at byte " + std::to_string(info.begin) +
                 " leaving a hole after byte " + std::to_string(position));
    position = info.end;
  }
  if (position != data_size)
    throw fail(std::to_string(data_size - position) + " bytes after the last tensor (corrupt header?)");

  if (data_size > 0) {
    state->mapping = MappedFile::map(fd, state->file_size, path);
  }
  return SafetensorsFile(std::move(state));
}

const std::filesystem::path& SafetensorsFile::path() const { return state_->path; }
uint64_t SafetensorsFile::file_size() const { return state_->file_size; }
uint64_t SafetensorsFile::header_size() const { return state_->header_size; }
const std::vector<std::string>& SafetensorsFile::keys() const { return state_->keys; }
bool SafetensorsFile::contains(const std::string& name) const { return state_->infos.count(name) != 0; }
const Metadata& SafetensorsFile::metadata() const { return state_->metadata; }

const TensorInfo& SafetensorsFile::info(const std::string& name) const {
  const auto it = state_->infos.find(name);
  if (it == state_->infos.end()) throw Error(state_->path.string() + ": no tensor " + quote_name(name));
  return it->second;
}

int64_t SafetensorsFile::num_elements() const {
  int64_t total = 0;
  for (const auto& [name, info] : state_->infos) total += info.numel();
  return total;
}

std::pair<const uint8_t*, size_t> SafetensorsFile::raw(const std::string& name) const {
  const TensorInfo& meta = info(name);
  if (meta.nbytes() == 0) return {nullptr, 0};
  return {state_->data(meta), static_cast<size_t>(meta.nbytes())};
}

torch::Tensor SafetensorsFile::tensor(const std::string& name, bool copy) const {
  const TensorInfo& meta = info(name);
  if (!meta.scalar_type)
    throw Error(state_->path.string() + ": tensor " + quote_name(name) + " has dtype " + meta.dtype +
                ", which this libtorch cannot represent");
  const auto options = torch::TensorOptions().dtype(*meta.scalar_type);
  if (meta.nbytes() == 0) return torch::empty(meta.shape, options);
  uint8_t* data = const_cast<uint8_t*>(state_->data(meta));
  const size_t itemsize = c10::elementSize(*meta.scalar_type);
  if (copy || reinterpret_cast<uintptr_t>(data) % itemsize != 0) {
    torch::Tensor out = torch::empty(meta.shape, options);
    std::memcpy(out.data_ptr(), data, meta.nbytes());
    return out;
  }
  std::shared_ptr<const MappedFile> keep = state_->mapping;
  return torch::from_blob(
      data, meta.shape, [keep](void*) mutable { keep.reset(); }, options);
}

NamedTensors SafetensorsFile::tensors(bool copy) const {
  NamedTensors out;
  out.reserve(state_->keys.size());
  for (const auto& key : state_->keys) out.emplace_back(key, tensor(key, copy));
  return out;
}

void save_safetensors(const std::filesystem::path& path, const NamedTensors& tensors,
                      const Metadata& metadata) {
  const std::string file = path.string();
  TensorStream stream;
  stream.specs.reserve(tensors.size());
  for (const auto& [name, tensor] : tensors) {
    if (!tensor.defined()) throw Error(file + ": tensor " + quote_name(name) + ": undefined tensor");
    if (tensor.is_sparse() || tensor.is_quantized())
      throw Error(file + ": tensor " + quote_name(name) + ": only dense tensors can be saved");
    stream.specs.push_back({name, tensor.sizes().vec(), tensor.scalar_type()});
  }
  stream.produce = [&tensors](size_t i) { return tensors[i].second; };
  save_safetensors(path, stream, metadata);
}

void save_safetensors(const std::filesystem::path& path, const TensorStream& stream,
                      const Metadata& metadata) {
  const std::string file = path.string();
  std::unordered_set<std::string> seen;
  nlohmann::ordered_json header = nlohmann::ordered_json::object();
  uint64_t offset = 0;
  for (const auto& spec : stream.specs) {
    const std::string& name = spec.name;
    auto bad = [&](const std::string& message) {
      return Error(file + ": tensor " + quote_name(name) + ": " + message);
    };
    if (name.empty()) throw Error(file + ": empty tensor name");
    if (name == "__metadata__") throw bad("reserved name");
    if (!seen.insert(name).second) throw bad("name given twice");
    std::string dtype;
    try {
      dtype = safetensors_dtype(spec.dtype);
    } catch (const Error& e) {
      throw bad(e.what());
    }
    uint64_t numel = 1;
    for (const int64_t d : spec.shape) {
      if (d < 0) throw bad("negative dimension");
      numel *= static_cast<uint64_t>(d);
    }
    const uint64_t nbytes = numel * c10::elementSize(spec.dtype);
    nlohmann::ordered_json entry = nlohmann::ordered_json::object();
    entry["dtype"] = dtype;
    entry["shape"] = spec.shape;
    entry["data_offsets"] = {offset, offset + nbytes};
    header[name] = std::move(entry);
    offset += nbytes;
  }
  if (!metadata.empty()) {
    nlohmann::ordered_json meta = nlohmann::ordered_json::object();
    for (const auto& [key, value] : metadata) meta[key] = value;
    header["__metadata__"] = std::move(meta);
  }
  std::string header_text;
  try {
    header_text = header.dump();
  } catch (const nlohmann::json::exception& e) {
    throw Error(file + ": cannot encode the header (names and metadata must be UTF-8): " + e.what());
  }
  header_text.append((8 - header_text.size() % 8) % 8, ' ');

  write_file_atomic(path, [&](std::ostream& out) {
    uint8_t length_bytes[8];
    uint64_t n = header_text.size();
    for (int i = 0; i < 8; ++i, n >>= 8) length_bytes[i] = static_cast<uint8_t>(n & 0xff);
    out.write(reinterpret_cast<const char*>(length_bytes), 8);
    out.write(header_text.data(), static_cast<std::streamsize>(header_text.size()));
    for (size_t i = 0; i < stream.specs.size(); ++i) {
      const TensorSpec& spec = stream.specs[i];
      const torch::Tensor cpu = stream.produce(i).detach().to(torch::kCPU).contiguous();
      if (cpu.sizes().vec() != spec.shape || cpu.scalar_type() != spec.dtype)
        throw Error(file + ": tensor " + quote_name(spec.name) + ": produced " +
                    c10::toString(cpu.scalar_type()) + " " + shape_string(cpu.sizes()) +
                    ", the header says " + c10::toString(spec.dtype) + " " + shape_string(spec.shape));
      out.write(static_cast<const char*>(cpu.data_ptr()),
                static_cast<std::streamsize>(cpu.numel() * cpu.element_size()));
    }
  });
}

}  // namespace dojo
