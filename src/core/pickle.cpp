#include "core/pickle.h"

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <map>
#include <unordered_map>

#include "core/error.h"

namespace dojo {
namespace {

using Kind = PickleValue::Kind;

PickleRef make(Kind kind) {
  auto value = std::make_shared<PickleValue>();
  value->kind = kind;
  return value;
}

PickleRef make_int(int64_t v) {
  auto value = make(Kind::kInt);
  value->integer = v;
  return value;
}

PickleRef make_text(Kind kind, std::string text) {
  auto value = make(kind);
  value->text = std::move(text);
  return value;
}

void append_utf8(std::string& out, uint32_t code) {
  if (code < 0x80) {
    out += static_cast<char>(code);
  } else if (code < 0x800) {
    out += static_cast<char>(0xC0 | (code >> 6));
    out += static_cast<char>(0x80 | (code & 0x3F));
  } else if (code < 0x10000) {
    out += static_cast<char>(0xE0 | (code >> 12));
    out += static_cast<char>(0x80 | ((code >> 6) & 0x3F));
    out += static_cast<char>(0x80 | (code & 0x3F));
  } else {
    out += static_cast<char>(0xF0 | (code >> 18));
    out += static_cast<char>(0x80 | ((code >> 12) & 0x3F));
    out += static_cast<char>(0x80 | ((code >> 6) & 0x3F));
    out += static_cast<char>(0x80 | (code & 0x3F));
  }
}

// The references a value holds, as slots that can be cleared.
std::vector<PickleRef*> child_slots(PickleValue& v) {
  std::vector<PickleRef*> slots;
  for (auto& c : v.items) slots.push_back(&c);
  for (auto& c : v.appended) slots.push_back(&c);
  for (auto& [k, x] : v.entries) {
    slots.push_back(&k);
    slots.push_back(&x);
  }
  if (v.state) slots.push_back(&v.state);
  return slots;
}

// Depth-first over the values reachable from `roots`; `on_cycle` gets each slot that points back
// at a value on the current path (the edge that closes a cycle). Iterative: no recursion.
void for_each_cycle_edge(const std::vector<PickleValue*>& roots,
                         const std::function<void(PickleRef&)>& on_cycle) {
  enum class Mark { kOnPath, kDone };
  std::unordered_map<const PickleValue*, Mark> marks;
  struct Frame {
    PickleValue* node;
    std::vector<PickleRef*> slots;
    size_t next = 0;
  };
  for (PickleValue* root : roots) {
    if (!root || marks.count(root)) continue;
    std::vector<Frame> path;
    marks[root] = Mark::kOnPath;
    path.push_back({root, child_slots(*root)});
    while (!path.empty()) {
      Frame& top = path.back();
      if (top.next == top.slots.size()) {
        marks[top.node] = Mark::kDone;
        path.pop_back();
        continue;
      }
      PickleRef& slot = *top.slots[top.next++];
      PickleValue* child = slot.get();
      if (!child) continue;
      const auto it = marks.find(child);
      if (it == marks.end()) {
        marks[child] = Mark::kOnPath;
        path.push_back({child, child_slots(*child)});
      } else if (it->second == Mark::kOnPath) {
        on_cycle(slot);
      }
    }
  }
}

class Machine {
 public:
  Machine(const uint8_t* data, uint64_t size, uint64_t offset, const PickleOptions& options)
      : data_(data), size_(size), pos_(offset), options_(options) {}
  Machine(const Machine&) = delete;
  Machine& operator=(const Machine&) = delete;
  // A pickle can make a value contain itself (a list appended to itself through the memo). Such
  // cycles would keep their values alive forever, so every edge closing one among the values
  // built here is cleared; run() has already refused a result that contained one.
  ~Machine() {
    std::vector<PickleRef> alive;
    for (const auto& weak : built_)
      if (auto node = weak.lock()) alive.push_back(std::move(node));
    std::vector<PickleValue*> roots;
    for (const auto& node : alive) roots.push_back(node.get());
    for_each_cycle_edge(roots, [](PickleRef& slot) { slot.reset(); });
  }

  PickleResult run() {
    for (;;) {
      op_start_ = pos_;
      const uint8_t op = byte();
      if (op == '.') {
        PickleResult result;
        result.value = pop();
        result.end = pos_;
        bool cyclic = false;
        for_each_cycle_edge({result.value.get()}, [&cyclic](PickleRef&) { cyclic = true; });
        if (cyclic) throw fail("the value contains itself (a cyclic pickle; checkpoints hold none)");
        return result;
      }
      step(op);
    }
  }

 private:
  Error fail(const std::string& message) const {
    return Error(options_.source + ": pickle byte " + std::to_string(op_start_) + ": " + message);
  }

  // --- reading the stream ---
  void need(uint64_t n) const {
    if (n > size_ - pos_) throw fail("truncated (needs " + std::to_string(n) + " more bytes)");
  }
  uint8_t byte() {
    need(1);
    return data_[pos_++];
  }
  uint64_t little(int n) {
    need(static_cast<uint64_t>(n));
    uint64_t v = 0;
    for (int i = n - 1; i >= 0; --i) v = (v << 8) | data_[pos_ + static_cast<uint64_t>(i)];
    pos_ += static_cast<uint64_t>(n);
    return v;
  }
  std::string bytes(uint64_t n) {
    need(n);
    std::string out(reinterpret_cast<const char*>(data_ + pos_), n);
    pos_ += n;
    return out;
  }
  std::string line() {
    const uint64_t start = pos_;
    while (pos_ < size_ && data_[pos_] != '\n') ++pos_;
    if (pos_ >= size_) throw fail("truncated (a text argument has no newline)");
    std::string out(reinterpret_cast<const char*>(data_ + start), pos_ - start);
    ++pos_;
    return out;
  }

  // --- the stack ---
  void push(PickleRef value) {
    built_.push_back(value);
    stack_.push_back(std::move(value));
  }
  PickleRef pop() {
    if (stack_.size() <= floor()) throw fail("pops an empty stack");
    PickleRef v = std::move(stack_.back());
    stack_.pop_back();
    return v;
  }
  PickleRef& top() {
    if (stack_.size() <= floor()) throw fail("reads an empty stack");
    return stack_.back();
  }
  size_t floor() const { return marks_.empty() ? 0 : marks_.back(); }
  std::vector<PickleRef> pop_mark() {
    if (marks_.empty()) throw fail("no MARK to pop to");
    const size_t mark = marks_.back();
    marks_.pop_back();
    std::vector<PickleRef> items(std::make_move_iterator(stack_.begin() + static_cast<std::ptrdiff_t>(mark)),
                                 std::make_move_iterator(stack_.end()));
    stack_.resize(mark);
    return items;
  }

  // --- globals and objects ---
  PickleRef global(std::string module, const std::string& name) {
    // Protocols <= 2 write Python 2 module names (pickle's fix_imports); name the Python 3 ones.
    static const std::map<std::string, std::string> python2_names = {
        {"__builtin__", "builtins"}, {"copy_reg", "copyreg"}, {"commands", "subprocess"},
        {"exceptions", "builtins"},  {"cPickle", "pickle"},   {"UserDict", "collections"}};
    if (const auto it = python2_names.find(module); it != python2_names.end()) module = it->second;
    const std::string dotted = module + "." + name;
    if (!options_.allowed_globals.count(dotted))
      throw fail("refuses global '" + dotted +
                 "': not a type that tensors or checkpoint metadata are made of (nothing was run)");
    return make_text(Kind::kGlobal, dotted);
  }
  const std::string& callable_name(const PickleRef& callable, const char* opcode) {
    if (!callable || callable->kind != Kind::kGlobal)
      throw fail(std::string(opcode) + " on a " + (callable ? callable->describe() : "null") +
                 ", not on a global");
    return callable->text;
  }
  PickleRef object(const std::string& name, std::vector<PickleRef> args) {
    if (name == "collections.OrderedDict") {
      auto dict = make(Kind::kDict);
      if (!args.empty() && args[0]->kind == Kind::kList)
        for (const auto& pair : args[0]->items)
          if (pair->kind == Kind::kTuple && pair->items.size() == 2)
            dict->entries.emplace_back(pair->items[0], pair->items[1]);
      return dict;
    }
    if (name == "torch.Size" || name == "builtins.set" || name == "builtins.frozenset") {
      auto out = make(name == "torch.Size" ? Kind::kTuple : Kind::kSet);
      if (!args.empty()) {
        if (args[0]->kind != Kind::kTuple && args[0]->kind != Kind::kList)
          throw fail(name + " of a " + args[0]->describe());
        out->items = args[0]->items;
      }
      return out;
    }
    auto obj = make_text(Kind::kObject, name);
    obj->items = std::move(args);
    return obj;
  }
  std::vector<PickleRef> tuple_items(const PickleRef& args, const char* opcode) {
    if (args->kind != Kind::kTuple)
      throw fail(std::string(opcode) + " arguments are a " + args->describe() + ", not a tuple");
    return args->items;
  }

  PickleRef memo_get(uint64_t index) {
    const auto it = memo_.find(index);
    if (it == memo_.end()) throw fail("memo entry " + std::to_string(index) + " was never stored");
    return it->second;
  }

  PickleRef integer_from_le(const std::string& raw) {
    if (raw.size() <= 8) {
      uint64_t v = 0;
      for (size_t i = raw.size(); i-- > 0;) v = (v << 8) | static_cast<uint8_t>(raw[i]);
      if (!raw.empty() && raw.size() < 8 && (static_cast<uint8_t>(raw.back()) & 0x80))
        v |= ~uint64_t{0} << (8 * raw.size());  // sign-extend
      return make_int(static_cast<int64_t>(v));
    }
    return make_text(Kind::kBigInt, raw);
  }
  PickleRef integer_from_text(std::string text) {
    if (!text.empty() && text.back() == 'L') text.pop_back();
    if (text.empty()) throw fail("empty integer");
    errno = 0;
    char* end = nullptr;
    const long long v = std::strtoll(text.c_str(), &end, 10);
    if (*end != '\0') throw fail("bad integer '" + text.substr(0, 40) + "'");
    if (errno == ERANGE) return make_text(Kind::kBigInt, text);  // decimal text; only compared, never used
    return make_int(v);
  }

  std::string unquote(const std::string& repr) {
    if (repr.size() < 2 || (repr[0] != '\'' && repr[0] != '"') || repr.back() != repr[0])
      throw fail("STRING argument is not quoted");
    std::string out;
    for (size_t i = 1; i + 1 < repr.size(); ++i) {
      char c = repr[i];
      if (c != '\\') {
        out += c;
        continue;
      }
      if (++i + 1 > repr.size() - 1) throw fail("STRING ends in a backslash");
      c = repr[i];
      switch (c) {
        case 'n':
          out += '\n';
          break;
        case 't':
          out += '\t';
          break;
        case 'r':
          out += '\r';
          break;
        case 'x': {
          if (i + 2 >= repr.size() - 1) throw fail("short \\x escape");
          out += static_cast<char>(std::strtol(repr.substr(i + 1, 2).c_str(), nullptr, 16));
          i += 2;
          break;
        }
        default:
          out += c;
      }
    }
    return out;
  }
  std::string raw_unicode(const std::string& raw) {
    std::string out;
    for (size_t i = 0; i < raw.size(); ++i) {
      const auto c = static_cast<uint8_t>(raw[i]);
      const size_t digits = raw[i] == '\\' && i + 1 < raw.size() ? (raw[i + 1] == 'u'   ? 4
                                                                    : raw[i + 1] == 'U' ? 8
                                                                                        : 0)
                                                                 : 0;
      if (digits && i + 2 + digits <= raw.size()) {
        const unsigned long code = std::strtoul(raw.substr(i + 2, digits).c_str(), nullptr, 16);
        append_utf8(out, static_cast<uint32_t>(std::min<unsigned long>(code, 0x10FFFF)));
        i += 1 + digits;
      } else {
        append_utf8(out, c);  // latin-1
      }
    }
    return out;
  }

  void add_to_container(PickleRef& target, std::vector<PickleRef> values, const char* opcode) {
    if (target->kind == Kind::kList)
      target->items.insert(target->items.end(), values.begin(), values.end());
    else if (target->kind == Kind::kObject)
      target->appended.insert(target->appended.end(), values.begin(), values.end());
    else
      throw fail(std::string(opcode) + " into a " + target->describe());
  }
  void set_items(PickleRef& target, std::vector<PickleRef> values, const char* opcode) {
    if (values.size() % 2 != 0) throw fail(std::string(opcode) + " with an odd number of items");
    if (target->kind != Kind::kDict && target->kind != Kind::kObject)
      throw fail(std::string(opcode) + " into a " + target->describe());
    for (size_t i = 0; i < values.size(); i += 2) target->entries.emplace_back(values[i], values[i + 1]);
  }

  void step(uint8_t op) {
    switch (op) {
      case 0x80: {  // PROTO
        const uint8_t version = byte();
        if (version > 5) throw fail("pickle protocol " + std::to_string(version) + " is newer than 5");
        return;
      }
      case 0x95:
        little(8);
        return;  // FRAME: a size hint
      case '(':
        marks_.push_back(stack_.size());
        return;
      case '0':  // POP
        if (stack_.size() > floor())
          stack_.pop_back();
        else
          pop_mark();
        return;
      case '1':
        pop_mark();
        return;
      case '2':
        push(top());
        return;
      case 'N':
        push(make(Kind::kNone));
        return;
      case 0x88:
      case 0x89: {
        auto v = make(Kind::kBool);
        v->boolean = op == 0x88;
        push(v);
        return;
      }
      case 'I': {
        const std::string text = line();
        if (text == "01" || text == "00") {
          auto v = make(Kind::kBool);
          v->boolean = text == "01";
          push(v);
        } else {
          push(integer_from_text(text));
        }
        return;
      }
      case 'L':
        push(integer_from_text(line()));
        return;
      case 'J':
        push(make_int(static_cast<int32_t>(static_cast<uint32_t>(little(4)))));
        return;
      case 'K':
        push(make_int(static_cast<int64_t>(little(1))));
        return;
      case 'M':
        push(make_int(static_cast<int64_t>(little(2))));
        return;
      case 0x8a:
        push(integer_from_le(bytes(little(1))));
        return;
      case 0x8b: {
        const auto n = static_cast<int32_t>(static_cast<uint32_t>(little(4)));
        if (n < 0) throw fail("LONG4 with a negative length");
        push(integer_from_le(bytes(static_cast<uint64_t>(n))));
        return;
      }
      case 'F': {
        const std::string text = line();
        char* end = nullptr;
        auto v = make(Kind::kFloat);
        v->number = std::strtod(text.c_str(), &end);
        if (end == text.c_str()) throw fail("bad float '" + text.substr(0, 40) + "'");
        push(v);
        return;
      }
      case 'G': {
        need(8);
        uint64_t bits = 0;
        for (int i = 0; i < 8; ++i) bits = (bits << 8) | data_[pos_++];  // big-endian
        auto v = make(Kind::kFloat);
        std::memcpy(&v->number, &bits, 8);
        push(v);
        return;
      }
      case 'S':
        push(make_text(Kind::kString, unquote(line())));
        return;
      case 'T': {
        const auto n = static_cast<int32_t>(static_cast<uint32_t>(little(4)));
        if (n < 0) throw fail("BINSTRING with a negative length");
        push(make_text(Kind::kString, bytes(static_cast<uint64_t>(n))));
        return;
      }
      case 'U':
        push(make_text(Kind::kString, bytes(little(1))));
        return;
      case 'V':
        push(make_text(Kind::kString, raw_unicode(line())));
        return;
      case 'X':
        push(make_text(Kind::kString, bytes(little(4))));
        return;
      case 0x8c:
        push(make_text(Kind::kString, bytes(little(1))));
        return;
      case 0x8d:
        push(make_text(Kind::kString, bytes(little(8))));
        return;
      case 'B':
        push(make_text(Kind::kBytes, bytes(little(4))));
        return;
      case 'C':
        push(make_text(Kind::kBytes, bytes(little(1))));
        return;
      case 0x8e:
      case 0x96:
        push(make_text(Kind::kBytes, bytes(little(8))));
        return;
      case ')':
        push(make(Kind::kTuple));
        return;
      case 't': {
        auto v = make(Kind::kTuple);
        v->items = pop_mark();
        push(v);
        return;
      }
      case 0x85:
      case 0x86:
      case 0x87: {
        const size_t n = op - 0x84;
        auto v = make(Kind::kTuple);
        v->items.resize(n);
        for (size_t i = n; i-- > 0;) v->items[i] = pop();
        push(v);
        return;
      }
      case ']':
        push(make(Kind::kList));
        return;
      case 'l': {
        auto v = make(Kind::kList);
        v->items = pop_mark();
        push(v);
        return;
      }
      case 'a': {
        PickleRef value = pop();
        add_to_container(top(), {value}, "APPEND");
        return;
      }
      case 'e': {
        auto values = pop_mark();
        add_to_container(top(), std::move(values), "APPENDS");
        return;
      }
      case '}':
        push(make(Kind::kDict));
        return;
      case 'd': {
        auto v = make(Kind::kDict);
        set_items(v, pop_mark(), "DICT");
        push(v);
        return;
      }
      case 's': {
        PickleRef value = pop();
        PickleRef key = pop();
        set_items(top(), {key, value}, "SETITEM");
        return;
      }
      case 'u': {
        auto values = pop_mark();
        set_items(top(), std::move(values), "SETITEMS");
        return;
      }
      case 0x8f:
        push(make(Kind::kSet));
        return;
      case 0x90: {
        auto values = pop_mark();
        PickleRef& set = top();
        if (set->kind != Kind::kSet) throw fail("ADDITEMS into a " + set->describe());
        set->items.insert(set->items.end(), values.begin(), values.end());
        return;
      }
      case 0x91: {
        auto v = make(Kind::kSet);
        v->items = pop_mark();
        push(v);
        return;
      }
      case 'g':
        push(memo_get(std::strtoull(line().c_str(), nullptr, 10)));
        return;
      case 'h':
        push(memo_get(little(1)));
        return;
      case 'j':
        push(memo_get(little(4)));
        return;
      case 'p':
        memo_[std::strtoull(line().c_str(), nullptr, 10)] = top();
        return;
      case 'q':
        memo_[little(1)] = top();
        return;
      case 'r':
        memo_[little(4)] = top();
        return;
      case 0x94: {
        const uint64_t index = memo_.size();
        memo_[index] = top();
        return;
      }
      case 'c': {
        const std::string module = line();
        push(global(module, line()));
        return;
      }
      case 0x93: {
        PickleRef name = pop();
        PickleRef module = pop();
        if (module->kind != Kind::kString || name->kind != Kind::kString)
          throw fail("STACK_GLOBAL of a " + module->describe() + " and a " + name->describe());
        push(global(module->text, name->text));
        return;
      }
      case 'R': {
        PickleRef args = pop();
        PickleRef callable = pop();
        const std::string name = callable_name(callable, "REDUCE");
        push(object(name, tuple_items(args, "REDUCE")));
        return;
      }
      case 0x81: {  // NEWOBJ: cls.__new__(cls, *args)
        PickleRef args = pop();
        PickleRef cls = pop();
        const std::string name = callable_name(cls, "NEWOBJ");
        push(object(name, tuple_items(args, "NEWOBJ")));
        return;
      }
      case 0x92: {  // NEWOBJ_EX: keyword arguments are kept as the object's state
        PickleRef kwargs = pop();
        PickleRef args = pop();
        PickleRef cls = pop();
        const std::string name = callable_name(cls, "NEWOBJ_EX");
        auto obj = object(name, tuple_items(args, "NEWOBJ_EX"));
        if (obj->kind == Kind::kObject) obj->state = kwargs;
        push(obj);
        return;
      }
      case 'i': {  // INST module\nname\n: class called on the items since MARK
        const std::string module = line();
        const std::string name = line();
        auto cls = global(module, name);
        push(object(cls->text, pop_mark()));
        return;
      }
      case 'o': {  // OBJ: MARK cls args...
        auto items = pop_mark();
        if (items.empty()) throw fail("OBJ with no class");
        const std::string name = callable_name(items[0], "OBJ");
        push(object(name, std::vector<PickleRef>(items.begin() + 1, items.end())));
        return;
      }
      case 'b': {
        PickleRef state = pop();
        PickleRef& target = top();
        if (target->kind == Kind::kObject)
          target->state = std::move(state);
        else if (target->kind != Kind::kDict)  // an OrderedDict's attributes (a state_dict's _metadata)
          throw fail("BUILD on a " + target->describe());
        return;
      }
      case 'P': {
        auto pid = make(Kind::kPersistentId);
        pid->state = make_text(Kind::kString, line());
        push(pid);
        return;
      }
      case 'Q': {
        auto pid = make(Kind::kPersistentId);
        pid->state = pop();
        push(pid);
        return;
      }
      case 0x82:
      case 0x83:
      case 0x84:
        throw fail("refuses an extension-registry code (EXT1/2/4): it names a global indirectly");
      case 0x97:
      case 0x98:
        throw fail("refuses out-of-band buffers (protocol 5 NEXT_BUFFER / READONLY_BUFFER)");
      default: {
        char hex[8];
        std::snprintf(hex, sizeof(hex), "0x%02x", op);
        throw fail(std::string("unknown opcode ") + hex);
      }
    }
  }

  const uint8_t* data_;
  uint64_t size_;
  uint64_t pos_;
  uint64_t op_start_ = 0;
  const PickleOptions& options_;
  std::vector<PickleRef> stack_;
  std::vector<size_t> marks_;
  std::unordered_map<uint64_t, PickleRef> memo_;
  std::vector<std::weak_ptr<PickleValue>> built_;  // every value pushed, for the destructor
};

}  // namespace

PickleValue::~PickleValue() {
  std::vector<PickleRef> pending;
  auto take = [&pending](PickleValue& v) {
    for (auto& c : v.items) pending.push_back(std::move(c));
    for (auto& c : v.appended) pending.push_back(std::move(c));
    for (auto& [k, x] : v.entries) {
      pending.push_back(std::move(k));
      pending.push_back(std::move(x));
    }
    if (v.state) pending.push_back(std::move(v.state));
    v.items.clear();
    v.appended.clear();
    v.entries.clear();
  };
  take(*this);
  while (!pending.empty()) {
    PickleRef node = std::move(pending.back());
    pending.pop_back();
    if (node && node.use_count() == 1) take(*node);
  }
}

const PickleValue* PickleValue::get(const std::string& key) const {
  for (const auto& [k, v] : entries)
    if (k && k->kind == Kind::kString && k->text == key) return v.get();
  return nullptr;
}

std::string PickleValue::describe() const {
  switch (kind) {
    case Kind::kNone:
      return "None";
    case Kind::kBool:
      return "bool";
    case Kind::kInt:
    case Kind::kBigInt:
      return "int";
    case Kind::kFloat:
      return "float";
    case Kind::kString:
      return "str";
    case Kind::kBytes:
      return "bytes";
    case Kind::kTuple:
      return "tuple";
    case Kind::kList:
      return "list";
    case Kind::kSet:
      return "set";
    case Kind::kDict:
      return "dict";
    case Kind::kGlobal:
      return "global " + text;
    case Kind::kObject:
      return "object of " + text;
    case Kind::kPersistentId:
      return "persistent id";
  }
  return "value";
}

PickleResult read_pickle(const uint8_t* data, uint64_t size, uint64_t offset, const PickleOptions& options) {
  if (offset > size) throw Error(options.source + ": pickle starts past the end");
  return Machine(data, size, offset, options).run();
}

std::set<std::string> torch_file_globals() {
  std::set<std::string> names = {
      "torch._utils._rebuild_tensor",
      "torch._utils._rebuild_tensor_v2",
      "torch._utils._rebuild_parameter",
      "torch._utils._rebuild_parameter_with_state",
      "collections.OrderedDict",
      "torch.Size",
      "torch.device",
      "builtins.set",
      "builtins.frozenset",
      // PyTorch Lightning's checkpoint containers (hyper-parameters).
      "argparse.Namespace",
      "pytorch_lightning.utilities.parsing.AttributeDict",
      "lightning_fabric.utilities.data.AttributeDict",
      "lightning.fabric.utilities.data.AttributeDict",
  };
  for (const char* storage :
       {"Double", "Float", "Half", "BFloat16", "Long", "Int", "Short", "Char", "Byte", "Bool"})
    names.insert(std::string("torch.") + storage + "Storage");
  for (const char* dtype : {"float64", "float32", "float16", "bfloat16", "int64", "int32", "int16", "int8",
                            "uint8", "bool", "double", "float", "half", "long", "int", "short"})
    names.insert(std::string("torch.") + dtype);
  return names;
}

std::set<std::string> dcp_metadata_globals() {
  std::set<std::string> names = torch_file_globals();
  for (const char* name :
       {"Metadata", "TensorStorageMetadata", "BytesStorageMetadata", "ChunkStorageMetadata",
        "TensorProperties", "MetadataIndex", "StorageMeta", "_MEM_FORMAT_ENCODING"})
    names.insert(std::string("torch.distributed.checkpoint.metadata.") + name);
  names.insert("torch.distributed.checkpoint.filesystem._StorageInfo");
  names.insert("torch.serialization._get_layout");
  for (const char* path : {"PosixPath", "PurePosixPath", "WindowsPath", "PureWindowsPath"})
    names.insert(std::string("pathlib.") + path);
  return names;
}

}  // namespace dojo
