// A Python pickle interpreter that builds values and never runs anything.
//
// torch.save files and distributed-checkpoint metadata are pickles. Python's unpickler calls
// whatever callable a pickle names (os.system included), so reading a user's file with it runs
// the file's code. This interpreter executes the opcodes (protocols 0-5) into an inert tree of
// PickleValue: a GLOBAL becomes a Global node holding its dotted name, and REDUCE / NEWOBJ /
// BUILD / INST / OBJ become Object nodes that record the callable's name, its arguments and its
// state. Nothing is imported or called. On top of that, a GLOBAL is accepted only when its name
// is in the caller's allow-list (torch's tensor rebuild functions, storage types, DCP's metadata
// classes, ...): any other name refuses the whole file with an error naming the global, so a
// file that would run code elsewhere is reported, not half-read. Extension codes (EXT1/2/4) and
// out-of-band buffers are refused too.
//
// Containers built by a few allowed globals become plain values: collections.OrderedDict is a
// Dict, torch.Size a Tuple, builtins.set / frozenset a Set. Memory is bounded by the input (no
// opcode allocates more than the bytes left), and nested values are freed without recursion.
#pragma once

#include <cstdint>
#include <memory>
#include <set>
#include <string>
#include <utility>
#include <vector>

namespace dojo {

struct PickleValue;
using PickleRef = std::shared_ptr<PickleValue>;

struct PickleValue {
  enum class Kind {
    kNone,
    kBool,
    kInt,     // fits int64: `integer`
    kBigInt,  // does not: `text` holds the little-endian two's-complement bytes
    kFloat,
    kString,  // UTF-8 (Python str) in `text`
    kBytes,   // Python bytes / protocol-2 str in `text`
    kTuple,
    kList,
    kSet,
    kDict,          // `entries`, in insertion order (keys may be any value)
    kGlobal,        // `text` = "module.name"
    kObject,        // `text` = the callable's "module.name"; `items` = its arguments;
                    // `state` = BUILD's argument; `entries` / `appended`: SETITEMS / APPENDS on it
    kPersistentId,  // `state` = the persistent id (torch: a tuple naming a storage)
  };
  Kind kind = Kind::kNone;
  bool boolean = false;
  int64_t integer = 0;
  double number = 0.0;
  std::string text;
  std::vector<PickleRef> items;
  std::vector<std::pair<PickleRef, PickleRef>> entries;
  std::vector<PickleRef> appended;
  PickleRef state;

  ~PickleValue();  // iterative: a deeply nested value does not overflow the stack

  bool is(Kind k) const { return kind == k; }
  bool is_string() const { return kind == Kind::kString || kind == Kind::kBytes; }
  // For a Dict (or an Object's SETITEMS entries) with string keys: the value under `key`, or null.
  const PickleValue* get(const std::string& key) const;
  // "None", "int", "str", "tuple", "dict", "object of torch._utils._rebuild_tensor_v2", ...
  std::string describe() const;
};

struct PickleOptions {
  // Dotted names ("collections.OrderedDict") a GLOBAL may name; any other name is refused.
  std::set<std::string> allowed_globals;
  // Names the file in errors.
  std::string source = "pickle";
};

struct PickleResult {
  PickleRef value;
  uint64_t end = 0;  // the offset just past the STOP opcode (legacy torch files hold several pickles)
};

// Interprets one pickle starting at data[offset]. Throws dojo::Error naming options.source, the
// byte offset and the problem (a refused global, a truncated stream, a malformed opcode).
PickleResult read_pickle(const uint8_t* data, uint64_t size, uint64_t offset, const PickleOptions& options);

// The globals torch.save archives use for tensors (_rebuild_tensor_v2, _rebuild_parameter, the
// typed storages, OrderedDict, torch.Size, dtypes, torch.device, set / frozenset) and the
// containers a PyTorch Lightning checkpoint adds (AttributeDict, argparse.Namespace).
std::set<std::string> torch_file_globals();
// torch_file_globals() plus what torch.distributed.checkpoint's .metadata names: its metadata
// dataclasses, _StorageInfo, torch.serialization._get_layout and pathlib paths.
std::set<std::string> dcp_metadata_globals();

}  // namespace dojo
