#include "core/torch_file.h"

#include <torch/torch.h>

#include <cstring>
#include <functional>
#include <unordered_set>

#include "core/error.h"
#include "core/zip_archive.h"

static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "torch.save data is read as host memory");

namespace dojo {
namespace {

using Kind = PickleValue::Kind;

// How deep a path of containers may go, and how many values one walk may visit: a pickle can
// make a small file describe a cyclic or exponentially shared graph.
constexpr int kMaxDepth = 64;
constexpr int64_t kMaxVisits = 50'000'000;

// The legacy format's first pickle: the integer 0x1950a86a20f9469cfc6c, little-endian bytes.
const std::string kLegacyMagic("\x6c\xfc\x9c\x46\xf9\x20\x6a\xa8\x50\x19", 10);

PickleOptions pickle_options(const std::string& source, const TorchFileOptions& options,
                             std::set<std::string> globals) {
  PickleOptions out;
  out.source = source;
  out.allowed_globals = std::move(globals);
  for (const auto& name : options.extra_globals) out.allowed_globals.insert(name);
  return out;
}

int64_t as_int(const PickleValue& v, const std::string& what, const std::string& source) {
  if (v.kind == Kind::kInt) return v.integer;
  if (v.kind == Kind::kBool) return v.boolean ? 1 : 0;
  throw Error(source + ": " + what + " is a " + v.describe() + ", not an int");
}

std::vector<int64_t> int_tuple(const PickleValue& v, const std::string& what, const std::string& source) {
  if (v.kind != Kind::kTuple && v.kind != Kind::kList)
    throw Error(source + ": " + what + " is a " + v.describe() + ", not a tuple");
  std::vector<int64_t> out;
  for (const auto& item : v.items) out.push_back(as_int(*item, what, source));
  return out;
}

// The storage a persistent id names: (typename, storage type, key, location, numel[, view]).
struct StorageRef {
  std::string key;
  torch::ScalarType dtype = torch::kFloat;
  int64_t numel = 0;
};

StorageRef storage_ref(const PickleValue& pid, const std::string& source) {
  const PickleValue* id = pid.kind == Kind::kPersistentId ? pid.state.get() : nullptr;
  if (!id || id->kind != Kind::kTuple || id->items.size() < 5 || !id->items[0]->is_string() ||
      id->items[0]->text != "storage")
    throw Error(source + ": a tensor's storage is a " + (id ? id->describe() : pid.describe()) +
                ", not a ('storage', type, key, location, numel) record");
  if (id->items[1]->kind != Kind::kGlobal)
    throw Error(source + ": a storage's type is a " + id->items[1]->describe());
  if (!id->items[2]->is_string() && id->items[2]->kind != Kind::kInt)
    throw Error(source + ": a storage's key is a " + id->items[2]->describe());
  if (id->items.size() > 5 && id->items[5]->kind != Kind::kNone)
    throw Error(source + ": storage views of the pre-0.4 format are not supported");
  StorageRef ref;
  ref.key = id->items[2]->kind == Kind::kInt ? std::to_string(id->items[2]->integer) : id->items[2]->text;
  ref.dtype = storage_scalar_type(id->items[1]->text);
  ref.numel = as_int(*id->items[4], "a storage's size", source);
  if (ref.numel < 0) throw Error(source + ": storage '" + ref.key + "' has a negative size");
  return ref;
}

// Every storage reference in the tree (cycle-safe), in first-seen order.
void collect_storages(const PickleValue& root, const std::string& source, std::vector<StorageRef>& out) {
  std::unordered_set<const PickleValue*> seen;
  std::vector<const PickleValue*> todo = {&root};
  while (!todo.empty()) {
    const PickleValue* v = todo.back();
    todo.pop_back();
    if (!v || !seen.insert(v).second) continue;
    if (v->kind == Kind::kPersistentId) {
      out.push_back(storage_ref(*v, source));
      continue;
    }
    for (const auto& c : v->items) todo.push_back(c.get());
    for (const auto& c : v->appended) todo.push_back(c.get());
    for (const auto& [k, x] : v->entries) {
      todo.push_back(k.get());
      todo.push_back(x.get());
    }
    todo.push_back(v->state.get());
  }
}

std::string key_text(const PickleValue& key) {
  switch (key.kind) {
    case Kind::kString:
    case Kind::kBytes:
      return key.text;
    case Kind::kInt:
      return std::to_string(key.integer);
    case Kind::kBool:
      return key.boolean ? "True" : "False";
    default:
      return "";
  }
}

}  // namespace

torch::ScalarType storage_scalar_type(const std::string& storage_type) {
  static const std::unordered_map<std::string, torch::ScalarType> table = {
      {"torch.DoubleStorage", torch::kFloat64}, {"torch.FloatStorage", torch::kFloat32},
      {"torch.HalfStorage", torch::kFloat16},   {"torch.BFloat16Storage", torch::kBFloat16},
      {"torch.LongStorage", torch::kInt64},     {"torch.IntStorage", torch::kInt32},
      {"torch.ShortStorage", torch::kInt16},    {"torch.CharStorage", torch::kInt8},
      {"torch.ByteStorage", torch::kUInt8},     {"torch.BoolStorage", torch::kBool}};
  const auto it = table.find(storage_type);
  if (it == table.end()) throw Error("unsupported storage type '" + storage_type + "'");
  return it->second;
}

torch::ScalarType pickled_scalar_type(const std::string& dtype_global) {
  static const std::unordered_map<std::string, torch::ScalarType> table = {
      {"torch.float64", torch::kFloat64},   {"torch.double", torch::kFloat64},
      {"torch.float32", torch::kFloat32},   {"torch.float", torch::kFloat32},
      {"torch.float16", torch::kFloat16},   {"torch.half", torch::kFloat16},
      {"torch.bfloat16", torch::kBFloat16}, {"torch.int64", torch::kInt64},
      {"torch.long", torch::kInt64},        {"torch.int32", torch::kInt32},
      {"torch.int", torch::kInt32},         {"torch.int16", torch::kInt16},
      {"torch.short", torch::kInt16},       {"torch.int8", torch::kInt8},
      {"torch.uint8", torch::kUInt8},       {"torch.bool", torch::kBool}};
  const auto it = table.find(dtype_global);
  if (it == table.end()) throw Error("unsupported dtype '" + dtype_global + "'");
  return it->second;
}

TorchFile TorchFile::from_archive(std::shared_ptr<const void> owner, const uint8_t* data, uint64_t size,
                                  const std::string& source, const TorchFileOptions& options) {
  TorchFile out;
  out.source_ = source;
  out.format_ = "zip";
  out.owner_ = std::move(owner);
  const ZipArchive zip = ZipArchive::parse(data, size, source);
  // The pickle is "<archive name>/data.pkl"; storages are "<archive name>/data/<key>".
  const ZipRecord* pickle = nullptr;
  for (const auto& record : zip.records()) {
    const auto slash = record.name.find('/');
    if (slash != std::string::npos && record.name.compare(slash, std::string::npos, "/data.pkl") == 0) {
      pickle = &record;
      break;
    }
  }
  if (!pickle) throw Error(source + ": a ZIP archive without a data.pkl record (not a torch.save file)");
  const std::string prefix = pickle->name.substr(0, pickle->name.size() - std::strlen("data.pkl"));
  if (const ZipRecord* order = zip.find(prefix + "byteorder")) {
    const auto text = zip.data(*order);
    if (text != "little")
      throw Error(source + ": byte order '" + std::string(text) + "' (only little-endian files are read)");
  }
  const std::string data_prefix = prefix + "data/";
  for (const auto& record : zip.records())
    if (record.name.compare(0, data_prefix.size(), data_prefix) == 0) {
      const auto bytes = zip.data(record);
      out.storages_[record.name.substr(data_prefix.size())] = {reinterpret_cast<const uint8_t*>(bytes.data()),
                                                               bytes.size()};
    }
  const auto pkl = zip.data(*pickle);
  out.root_ = read_pickle(reinterpret_cast<const uint8_t*>(pkl.data()), pkl.size(), 0,
                          pickle_options(source, options, torch_file_globals()))
                  .value;
  return out;
}

TorchFile TorchFile::open(const std::filesystem::path& path, const TorchFileOptions& options) {
  const auto file = MappedFile::open(path);
  return from_bytes(file, file->bytes(), file->size, path.string(), options);
}

TorchFile TorchFile::from_bytes(std::shared_ptr<const void> owner, const uint8_t* data, uint64_t size,
                                const std::string& source, const TorchFileOptions& options) {
  if (ZipArchive::looks_like_zip(data, size)) return from_archive(owner, data, size, source, options);
  if (size < 2 || data[0] != 0x80)
    throw Error(source + ": neither a torch.save ZIP archive nor a legacy torch.save pickle");

  // Legacy: magic number, protocol version, system info, the object, the storage keys, then each
  // storage as an int64 element count followed by its bytes, in the keys' order.
  TorchFile out;
  out.source_ = source;
  out.format_ = "legacy";
  out.owner_ = std::move(owner);
  const PickleOptions opts = pickle_options(source, options, torch_file_globals());
  auto magic = read_pickle(data, size, 0, opts);
  if (magic.value->kind != Kind::kBigInt || magic.value->text != kLegacyMagic)
    throw Error(source + ": a pickle, but not a torch.save file (no torch magic number)");
  auto version = read_pickle(data, size, magic.end, opts);
  if (version.value->kind != Kind::kInt || version.value->integer != 1001)
    throw Error(source + ": legacy torch.save protocol version is not 1001");
  auto sys_info = read_pickle(data, size, version.end, opts);
  auto object = read_pickle(data, size, sys_info.end, opts);
  auto keys = read_pickle(data, size, object.end, opts);
  if (keys.value->kind != Kind::kList)
    throw Error(source + ": the storage key list is a " + keys.value->describe());
  out.root_ = object.value;

  std::vector<StorageRef> refs;
  collect_storages(*out.root_, source, refs);
  std::unordered_map<std::string, StorageRef> by_key;
  for (const auto& ref : refs) by_key.emplace(ref.key, ref);
  uint64_t pos = keys.end;
  for (const auto& key_value : keys.value->items) {
    const std::string key = key_text(*key_value);
    const auto it = by_key.find(key);
    if (it == by_key.end()) throw Error(source + ": storage '" + key + "' is listed but never used");
    if (size - pos < 8) throw Error(source + ": truncated before storage '" + key + "'");
    int64_t numel = 0;
    std::memcpy(&numel, data + pos, 8);
    pos += 8;
    const uint64_t itemsize = c10::elementSize(it->second.dtype);
    if (numel < 0 || static_cast<uint64_t>(numel) > (size - pos) / itemsize)
      throw Error(source + ": storage '" + key + "' claims " + std::to_string(numel) +
                  " elements, more than the file holds");
    out.storages_[key] = {data + pos, static_cast<uint64_t>(numel) * itemsize};
    pos += static_cast<uint64_t>(numel) * itemsize;
  }
  return out;
}

const PickleValue& TorchFile::at(const std::string& path) const {
  if (path.empty()) return *root_;
  // Match keys greedily: "a.b.c" may be key "a" then "b.c", or key "a.b" then "c".
  std::function<const PickleValue*(const PickleValue&, const std::string&, int)> find =
      [&](const PickleValue& v, const std::string& rest, int depth) -> const PickleValue* {
    if (rest.empty()) return &v;
    if (depth > kMaxDepth) return nullptr;
    if (v.kind == Kind::kList || v.kind == Kind::kTuple) {  // "optimizer_states.0..." indexes a list
      const auto dot = rest.find('.');
      const std::string index = rest.substr(0, dot);
      if (index.empty() || index.find_first_not_of("0123456789") != std::string::npos || index.size() > 9)
        return nullptr;
      const size_t i = std::stoul(index);
      if (i >= v.items.size() || !v.items[i]) return nullptr;
      return dot == std::string::npos ? v.items[i].get() : find(*v.items[i], rest.substr(dot + 1), depth + 1);
    }
    for (const auto& [k, x] : v.entries) {
      if (!k || !x) continue;
      const std::string key = key_text(*k);
      if (key.empty() || rest.compare(0, key.size(), key) != 0) continue;
      if (rest.size() == key.size()) return x.get();
      if (rest[key.size()] == '.')
        if (const PickleValue* hit = find(*x, rest.substr(key.size() + 1), depth + 1)) return hit;
    }
    return nullptr;
  };
  const PickleValue* hit = find(*root_, path, 0);
  if (!hit) throw Error(source_ + ": no entry '" + path + "'");
  return *hit;
}

bool TorchFile::is_tensor(const PickleValue& value) {
  return value.kind == Kind::kObject &&
         (value.text == "torch._utils._rebuild_tensor_v2" || value.text == "torch._utils._rebuild_tensor" ||
          value.text == "torch._utils._rebuild_parameter" ||
          value.text == "torch._utils._rebuild_parameter_with_state");
}

torch::Tensor TorchFile::tensor(const PickleValue& value) const {
  if (!is_tensor(value)) throw Error(source_ + ": a " + value.describe() + " is not a tensor");
  // A parameter wraps the tensor record it was made from (never more than a level or two).
  const PickleValue* record = &value;
  for (int level = 0; record->text == "torch._utils._rebuild_parameter" ||
                      record->text == "torch._utils._rebuild_parameter_with_state";
       ++level) {
    if (level > 4 || record->items.empty() || !is_tensor(*record->items[0]))
      throw Error(source_ + ": a parameter record without its tensor");
    record = record->items[0].get();
  }
  const auto& args = record->items;
  if (args.size() < 4)
    throw Error(source_ + ": a tensor record with " + std::to_string(args.size()) + " arguments");
  return rebuild(*args[0], as_int(*args[1], "a tensor's storage offset", source_), *args[2], *args[3]);
}

torch::Tensor TorchFile::rebuild(const PickleValue& storage_id, int64_t offset, const PickleValue& size_value,
                                 const PickleValue& stride_value) const {
  const StorageRef ref = storage_ref(storage_id, source_);
  const auto size = int_tuple(size_value, "a tensor's size", source_);
  const auto stride = int_tuple(stride_value, "a tensor's stride", source_);
  const auto it = storages_.find(ref.key);
  if (it == storages_.end()) throw Error(source_ + ": storage '" + ref.key + "' is not in the file");
  const uint64_t itemsize = c10::elementSize(ref.dtype);
  const uint64_t available = it->second.nbytes / itemsize;
  if (static_cast<uint64_t>(ref.numel) > available)
    throw Error(source_ + ": storage '" + ref.key + "' holds " + std::to_string(available) +
                " elements, not " + std::to_string(ref.numel));
  if (size.size() != stride.size())
    throw Error(source_ + ": a tensor of storage '" + ref.key + "' has " + std::to_string(size.size()) +
                " sizes but " + std::to_string(stride.size()) + " strides");
  // The last element the view reaches must lie inside the storage.
  bool empty = false;
  __int128 last = offset;
  for (size_t d = 0; d < size.size(); ++d) {
    if (size[d] < 0 || stride[d] < 0)
      throw Error(source_ + ": a tensor of storage '" + ref.key + "' has a negative size or stride");
    if (size[d] == 0)
      empty = true;
    else
      last += static_cast<__int128>(size[d] - 1) * stride[d];
  }
  if (offset < 0 || (!empty && last >= ref.numel))
    throw Error(source_ + ": a tensor reaches past the end of storage '" + ref.key + "' (" +
                std::to_string(ref.numel) + " elements)");
  const auto options = torch::TensorOptions().dtype(ref.dtype);
  if (empty || ref.numel == 0) return torch::empty(size, options);
  torch::Tensor& storage = storage_tensors_[ref.key];
  if (!storage.defined() || storage.scalar_type() != ref.dtype || storage.numel() < ref.numel) {
    uint8_t* base = const_cast<uint8_t*>(it->second.data);
    if (reinterpret_cast<uintptr_t>(base) % itemsize == 0) {
      std::shared_ptr<const void> keep = owner_;
      storage = torch::from_blob(
          base, {ref.numel}, [keep](void*) mutable { keep.reset(); }, options);
    } else {
      storage = torch::empty({ref.numel}, options);
      std::memcpy(storage.data_ptr(), base, static_cast<size_t>(ref.numel) * itemsize);
    }
  }
  return storage.as_strided(size, stride, offset);
}

NamedTensors TorchFile::tensors(const std::string& path) const {
  NamedTensors out;
  int64_t visits = 0;
  std::function<void(const PickleValue&, const std::string&, int)> walk =
      [&](const PickleValue& v, const std::string& name, int depth) {
        if (++visits > kMaxVisits)
          throw Error(source_ + ": more than " + std::to_string(kMaxVisits) + " values to walk");
        if (depth > kMaxDepth)
          throw Error(source_ + ": containers nested deeper than " + std::to_string(kMaxDepth) +
                      " levels at '" + name + "'");
        if (is_tensor(v)) {
          if (name.empty())
            throw Error(source_ + ": the tensor has no name (the file holds a single tensor)");
          out.emplace_back(name, tensor(v));
          return;
        }
        auto join = [&name](const std::string& key) { return name.empty() ? key : name + "." + key; };
        if (v.kind == Kind::kList || v.kind == Kind::kTuple)
          for (size_t i = 0; i < v.items.size(); ++i) walk(*v.items[i], join(std::to_string(i)), depth + 1);
        for (const auto& [k, x] : v.entries) {
          const std::string key = k ? key_text(*k) : "";
          if (!key.empty() && x) walk(*x, join(key), depth + 1);
        }
      };
  walk(at(path), "", 0);
  return out;
}

}  // namespace dojo
