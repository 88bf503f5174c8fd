#include "io/parquet.h"

#include <snappy-c.h>
#include <zstd.h>

#include <cstring>
#include <fstream>
#include <limits>

#include "core/error.h"

namespace dojo::io {

std::string to_string(ParquetType type) {
  switch (type) {
    case ParquetType::kBoolean:
      return "bool";
    case ParquetType::kInt32:
      return "int32";
    case ParquetType::kInt64:
      return "int64";
    case ParquetType::kInt96:
      return "int96";
    case ParquetType::kFloat:
      return "float";
    case ParquetType::kDouble:
      return "double";
    case ParquetType::kByteArray:
      return "string";
    case ParquetType::kFixedLenByteArray:
      return "fixed_len_byte_array";
  }
  return "unknown";
}

namespace {

// Page types, encodings and codecs of parquet.thrift that the reader knows.
enum PageType { kDataPage = 0, kIndexPage = 1, kDictionaryPage = 2, kDataPageV2 = 3 };
enum Encoding { kPlain = 0, kPlainDictionary = 2, kRle = 3, kBitPacked = 4, kRleDictionary = 8 };
enum Codec { kUncompressed = 0, kSnappy = 1, kZstd = 6 };

// Thrift compact protocol element types.
enum CType {
  kStop = 0,
  kBoolTrue = 1,
  kBoolFalse = 2,
  kByte = 3,
  kI16 = 4,
  kI32 = 5,
  kI64 = 6,
  kDouble = 7,
  kBinary = 8,
  kList = 9,
  kSet = 10,
  kMap = 11,
  kStruct = 12
};

constexpr int kMaxThriftDepth = 32;

// A bounds-checked cursor over bytes; every failure names the file and what was being read.
class Cursor {
 public:
  Cursor(const uint8_t* data, size_t size, const std::string* where)
      : data_(data), size_(size), where_(where) {}

  size_t remaining() const { return size_ - pos_; }
  size_t pos() const { return pos_; }
  const uint8_t* here() const { return data_ + pos_; }

  [[noreturn]] void fail(const std::string& what) const { throw Error(*where_ + ": " + what); }

  uint8_t byte() {
    if (pos_ >= size_) fail("truncated data");
    return data_[pos_++];
  }
  const uint8_t* take(size_t n, const char* what) {
    if (n > remaining()) fail(std::string("truncated ") + what);
    const uint8_t* p = data_ + pos_;
    pos_ += n;
    return p;
  }
  uint64_t varint() {
    uint64_t result = 0;
    for (int shift = 0; shift < 64; shift += 7) {
      const uint8_t b = byte();
      result |= static_cast<uint64_t>(b & 0x7f) << shift;
      if (!(b & 0x80)) return result;
    }
    fail("varint longer than 10 bytes");
  }
  uint32_t u32le() {
    const uint8_t* p = take(4, "32-bit length");
    return uint32_t(p[0]) | uint32_t(p[1]) << 8 | uint32_t(p[2]) << 16 | uint32_t(p[3]) << 24;
  }

 private:
  const uint8_t* data_;
  size_t size_;
  size_t pos_ = 0;
  const std::string* where_;
};

int64_t zigzag(uint64_t v) { return static_cast<int64_t>(v >> 1) ^ -static_cast<int64_t>(v & 1); }

// Thrift compact protocol decoding: just what the footer and page headers need.
class Compact {
 public:
  explicit Compact(Cursor& c) : c_(c) {}
  Cursor& cursor() { return c_; }

  int64_t i64() { return zigzag(c_.varint()); }
  int32_t i32() {
    const int64_t v = i64();
    if (v < std::numeric_limits<int32_t>::min() || v > std::numeric_limits<int32_t>::max())
      c_.fail("thrift i32 out of range");
    return static_cast<int32_t>(v);
  }
  std::string binary() {
    const uint64_t n = c_.varint();
    if (n > c_.remaining()) c_.fail("truncated thrift string");
    const uint8_t* p = c_.take(static_cast<size_t>(n), "thrift string");
    return std::string(reinterpret_cast<const char*>(p), static_cast<size_t>(n));
  }
  // Returns {element type, size}; the size is checked against the bytes left (every element
  // takes at least one byte), so a corrupt count cannot make callers allocate.
  std::pair<int, uint64_t> list_header() {
    const uint8_t b = c_.byte();
    uint64_t size = b >> 4;
    if (size == 15) size = c_.varint();
    if (size > c_.remaining()) c_.fail("thrift list longer than the data");
    return {b & 0x0f, size};
  }

  void skip(int type, int depth) {
    if (depth > kMaxThriftDepth) c_.fail("thrift nesting too deep");
    switch (type) {
      case kBoolTrue:
      case kBoolFalse:
        return;  // value lives in the field header
      case kByte:
        c_.byte();
        return;
      case kI16:
      case kI32:
      case kI64:
        c_.varint();
        return;
      case kDouble:
        c_.take(8, "thrift double");
        return;
      case kBinary:
        binary();
        return;
      case kList:
      case kSet: {
        const auto [elem, size] = list_header();
        for (uint64_t i = 0; i < size; ++i) skip_element(elem, depth + 1);
        return;
      }
      case kMap: {
        const uint64_t size = c_.varint();
        if (size == 0) return;
        if (size > c_.remaining()) c_.fail("thrift map longer than the data");
        const uint8_t kv = c_.byte();
        for (uint64_t i = 0; i < size; ++i) {
          skip_element(kv >> 4, depth + 1);
          skip_element(kv & 0x0f, depth + 1);
        }
        return;
      }
      case kStruct:
        read_struct(depth + 1, [](int16_t, int) { return false; });
        return;
      default:
        c_.fail("unknown thrift type " + std::to_string(type));
    }
  }

  // Calls on_field(id, type) for each field; when it returns false the field is skipped.
  template <typename F>
  void read_struct(int depth, F&& on_field) {
    if (depth > kMaxThriftDepth) c_.fail("thrift nesting too deep");
    int16_t last = 0;
    while (true) {
      const uint8_t b = c_.byte();
      if (b == kStop) return;
      const int type = b & 0x0f;
      const int delta = b >> 4;
      int16_t id;
      if (delta != 0) {
        id = static_cast<int16_t>(last + delta);
      } else {
        const int64_t v = zigzag(c_.varint());
        if (v < std::numeric_limits<int16_t>::min() || v > std::numeric_limits<int16_t>::max())
          c_.fail("thrift field id out of range");
        id = static_cast<int16_t>(v);
      }
      last = id;
      if (!on_field(id, type)) skip(type, depth + 1);
    }
  }

  void expect(int actual, int wanted, const char* field) {
    if (actual != wanted) c_.fail(std::string("thrift field '") + field + "' has the wrong type");
  }
  bool boolean(int type, const char* field) {
    if (type != kBoolTrue && type != kBoolFalse)
      c_.fail(std::string("thrift field '") + field + "' is not bool");
    return type == kBoolTrue;
  }

 private:
  // List elements: bools are a whole byte, everything else as in a field.
  void skip_element(int type, int depth) {
    if (type == kBoolTrue || type == kBoolFalse) {
      c_.byte();
      return;
    }
    skip(type, depth);
  }

  Cursor& c_;
};

struct SchemaElement {
  int type = -1;
  int type_length = 0;
  int repetition = 0;
  std::string name;
  int num_children = 0;
  int converted_type = -1;
};

struct ColumnMeta {
  int type = -1;
  std::vector<std::string> path;
  int codec = 0;
  int64_t num_values = 0;
  int64_t total_compressed_size = 0;
  int64_t data_page_offset = -1;
  int64_t dictionary_page_offset = -1;
};

struct ColumnChunk {
  std::string file_path;
  bool has_meta = false;
  ColumnMeta meta;
};

struct RowGroup {
  std::vector<ColumnChunk> columns;
  int64_t num_rows = 0;
};

struct PageHeader {
  int type = -1;
  int32_t uncompressed_size = -1;
  int32_t compressed_size = -1;
  bool has_data = false, has_dict = false, has_v2 = false;
  int32_t num_values = 0;
  int32_t encoding = 0;
  int32_t def_encoding = kRle, rep_encoding = kRle;
  int32_t def_length = 0, rep_length = 0;  // V2
  bool is_compressed = true;               // V2
};

SchemaElement read_schema_element(Compact& p, int depth) {
  SchemaElement e;
  p.read_struct(depth, [&](int16_t id, int type) {
    switch (id) {
      case 1:
        p.expect(type, kI32, "SchemaElement.type"), e.type = p.i32();
        return true;
      case 2:
        p.expect(type, kI32, "SchemaElement.type_length"), e.type_length = p.i32();
        return true;
      case 3:
        p.expect(type, kI32, "SchemaElement.repetition_type"), e.repetition = p.i32();
        return true;
      case 4:
        p.expect(type, kBinary, "SchemaElement.name"), e.name = p.binary();
        return true;
      case 5:
        p.expect(type, kI32, "SchemaElement.num_children"), e.num_children = p.i32();
        return true;
      case 6:
        p.expect(type, kI32, "SchemaElement.converted_type"), e.converted_type = p.i32();
        return true;
      default:
        return false;
    }
  });
  return e;
}

ColumnMeta read_column_meta(Compact& p, int depth) {
  ColumnMeta m;
  p.read_struct(depth, [&](int16_t id, int type) {
    switch (id) {
      case 1:
        p.expect(type, kI32, "ColumnMetaData.type"), m.type = p.i32();
        return true;
      case 3: {
        p.expect(type, kList, "ColumnMetaData.path_in_schema");
        const auto [elem, size] = p.list_header();
        if (elem != kBinary) p.cursor().fail("ColumnMetaData.path_in_schema is not a string list");
        for (uint64_t i = 0; i < size; ++i) m.path.push_back(p.binary());
        return true;
      }
      case 4:
        p.expect(type, kI32, "ColumnMetaData.codec"), m.codec = p.i32();
        return true;
      case 5:
        p.expect(type, kI64, "ColumnMetaData.num_values"), m.num_values = p.i64();
        return true;
      case 7:
        p.expect(type, kI64, "ColumnMetaData.total_compressed_size"), m.total_compressed_size = p.i64();
        return true;
      case 9:
        p.expect(type, kI64, "ColumnMetaData.data_page_offset"), m.data_page_offset = p.i64();
        return true;
      case 11:
        p.expect(type, kI64, "ColumnMetaData.dictionary_page_offset"), m.dictionary_page_offset = p.i64();
        return true;
      default:
        return false;
    }
  });
  return m;
}

ColumnChunk read_column_chunk(Compact& p, int depth) {
  ColumnChunk c;
  p.read_struct(depth, [&](int16_t id, int type) {
    switch (id) {
      case 1:
        p.expect(type, kBinary, "ColumnChunk.file_path"), c.file_path = p.binary();
        return true;
      case 3:
        p.expect(type, kStruct, "ColumnChunk.meta_data");
        c.meta = read_column_meta(p, depth + 1);
        c.has_meta = true;
        return true;
      default:
        return false;
    }
  });
  return c;
}

RowGroup read_row_group(Compact& p, int depth) {
  RowGroup g;
  p.read_struct(depth, [&](int16_t id, int type) {
    switch (id) {
      case 1: {
        p.expect(type, kList, "RowGroup.columns");
        const auto [elem, size] = p.list_header();
        if (elem != kStruct) p.cursor().fail("RowGroup.columns is not a struct list");
        for (uint64_t i = 0; i < size; ++i) g.columns.push_back(read_column_chunk(p, depth + 1));
        return true;
      }
      case 3:
        p.expect(type, kI64, "RowGroup.num_rows"), g.num_rows = p.i64();
        return true;
      default:
        return false;
    }
  });
  return g;
}

PageHeader read_page_header(Compact& p) {
  PageHeader h;
  p.read_struct(0, [&](int16_t id, int type) {
    switch (id) {
      case 1:
        p.expect(type, kI32, "PageHeader.type"), h.type = p.i32();
        return true;
      case 2:
        p.expect(type, kI32, "PageHeader.uncompressed_page_size"), h.uncompressed_size = p.i32();
        return true;
      case 3:
        p.expect(type, kI32, "PageHeader.compressed_page_size"), h.compressed_size = p.i32();
        return true;
      case 5:
        p.expect(type, kStruct, "PageHeader.data_page_header");
        h.has_data = true;
        p.read_struct(1, [&](int16_t fid, int ftype) {
          switch (fid) {
            case 1:
              p.expect(ftype, kI32, "DataPageHeader.num_values"), h.num_values = p.i32();
              return true;
            case 2:
              p.expect(ftype, kI32, "DataPageHeader.encoding"), h.encoding = p.i32();
              return true;
            case 3:
              p.expect(ftype, kI32, "DataPageHeader.definition_level_encoding"), h.def_encoding = p.i32();
              return true;
            case 4:
              p.expect(ftype, kI32, "DataPageHeader.repetition_level_encoding"), h.rep_encoding = p.i32();
              return true;
            default:
              return false;
          }
        });
        return true;
      case 7:
        p.expect(type, kStruct, "PageHeader.dictionary_page_header");
        h.has_dict = true;
        p.read_struct(1, [&](int16_t fid, int ftype) {
          switch (fid) {
            case 1:
              p.expect(ftype, kI32, "DictionaryPageHeader.num_values"), h.num_values = p.i32();
              return true;
            case 2:
              p.expect(ftype, kI32, "DictionaryPageHeader.encoding"), h.encoding = p.i32();
              return true;
            default:
              return false;
          }
        });
        return true;
      case 8:
        p.expect(type, kStruct, "PageHeader.data_page_header_v2");
        h.has_v2 = true;
        p.read_struct(1, [&](int16_t fid, int ftype) {
          switch (fid) {
            case 1:
              p.expect(ftype, kI32, "DataPageHeaderV2.num_values"), h.num_values = p.i32();
              return true;
            case 4:
              p.expect(ftype, kI32, "DataPageHeaderV2.encoding"), h.encoding = p.i32();
              return true;
            case 5:
              p.expect(ftype, kI32, "DataPageHeaderV2.definition_levels_byte_length"), h.def_length = p.i32();
              return true;
            case 6:
              p.expect(ftype, kI32, "DataPageHeaderV2.repetition_levels_byte_length"), h.rep_length = p.i32();
              return true;
            case 7:
              h.is_compressed = p.boolean(ftype, "DataPageHeaderV2.is_compressed");
              return true;
            default:
              return false;
          }
        });
        return true;
      default:
        return false;
    }
  });
  return h;
}

// A leaf column with the levels its position in the schema implies.
struct Leaf {
  std::vector<std::string> path;
  ParquetType type = ParquetType::kInt32;
  int type_length = 0;
  int max_def = 0;
  int max_rep = 0;
  bool optional = false;  // the leaf itself
  size_t top = 0;         // index of its top-level field
};

// Everything decoded from one leaf column across all row groups.
struct Decoded {
  std::vector<uint8_t> def, rep;  // one per level entry; empty when the max level is 0
  int64_t entries = 0;
  std::vector<int64_t> ints;         // BOOLEAN, INT32, INT64 (non-null values, in order)
  std::vector<double> reals;         // FLOAT, DOUBLE
  std::vector<std::string> strings;  // BYTE_ARRAY, FIXED_LEN_BYTE_ARRAY, INT96
  int64_t string_bytes = 0;          // total size of `strings`, checked against the limits
  size_t value_count() const { return ints.size() + reals.size() + strings.size(); }
};

int bit_width(int max_level) {
  int w = 0;
  while ((1 << w) <= max_level) ++w;
  return w;
}

// RLE / bit-packed hybrid: appends `count` values of `width` bits to `out`.
template <typename T>
void decode_hybrid(Cursor& c, int width, int64_t count, std::vector<T>& out, const char* what) {
  if (width < 0 || width > 32)
    c.fail(std::string(what) + ": bit width " + std::to_string(width) + " out of range");
  const int64_t target = static_cast<int64_t>(out.size()) + count;
  const uint64_t mask = width == 32 ? 0xffffffffull : ((1ull << width) - 1);
  while (static_cast<int64_t>(out.size()) < target) {
    if (c.remaining() == 0)
      c.fail(std::string(what) + ": data ends before " + std::to_string(count) + " values");
    const uint64_t header = c.varint();
    if (header & 1) {
      // Bit-packed: (header >> 1) groups of 8 values, LSB first.
      const uint64_t groups = header >> 1;
      // Width 0 takes no bytes; the loop below stops at `target` whatever the group count.
      if (width > 0 && groups > c.remaining())
        c.fail(std::string(what) + ": bit-packed run longer than the data");
      const uint64_t bytes = groups * static_cast<uint64_t>(width);
      const uint8_t* p = c.take(static_cast<size_t>(bytes), what);
      const uint64_t n = groups * 8;
      uint64_t bit = 0;
      for (uint64_t i = 0; i < n && static_cast<int64_t>(out.size()) < target; ++i) {
        uint64_t v = 0;
        for (int b = 0; b < width; ++b, ++bit)
          v |= static_cast<uint64_t>((p[bit >> 3] >> (bit & 7)) & 1) << b;
        out.push_back(static_cast<T>(v & mask));
      }
    } else {
      const uint64_t run = header >> 1;
      const int value_bytes = (width + 7) / 8;
      const uint8_t* p = c.take(static_cast<size_t>(value_bytes), what);
      uint64_t v = 0;
      for (int b = 0; b < value_bytes; ++b) v |= static_cast<uint64_t>(p[b]) << (8 * b);
      if (v > mask) c.fail(std::string(what) + ": run value wider than the bit width");
      const uint64_t left = static_cast<uint64_t>(target - static_cast<int64_t>(out.size()));
      out.insert(out.end(), static_cast<size_t>(run < left ? run : left), static_cast<T>(v));
    }
  }
}

// PLAIN values of one physical type appended to `d`.
void decode_plain(Cursor& c, const Leaf& leaf, int64_t n, Decoded& d) {
  auto fixed = [&](size_t size) {
    if (static_cast<uint64_t>(n) > c.remaining() / size) c.fail("PLAIN values longer than the page");
    return c.take(static_cast<size_t>(n) * size, "PLAIN values");
  };
  switch (leaf.type) {
    case ParquetType::kBoolean: {
      const uint64_t bytes = (static_cast<uint64_t>(n) + 7) / 8;
      if (bytes > c.remaining()) c.fail("PLAIN booleans longer than the page");
      const uint8_t* p = c.take(static_cast<size_t>(bytes), "PLAIN booleans");
      for (int64_t i = 0; i < n; ++i) d.ints.push_back((p[i >> 3] >> (i & 7)) & 1);
      return;
    }
    case ParquetType::kInt32: {
      const uint8_t* p = fixed(4);
      for (int64_t i = 0; i < n; ++i) {
        int32_t v;
        std::memcpy(&v, p + 4 * i, 4);
        d.ints.push_back(v);
      }
      return;
    }
    case ParquetType::kInt64: {
      const uint8_t* p = fixed(8);
      for (int64_t i = 0; i < n; ++i) {
        int64_t v;
        std::memcpy(&v, p + 8 * i, 8);
        d.ints.push_back(v);
      }
      return;
    }
    case ParquetType::kFloat: {
      const uint8_t* p = fixed(4);
      for (int64_t i = 0; i < n; ++i) {
        float v;
        std::memcpy(&v, p + 4 * i, 4);
        d.reals.push_back(v);
      }
      return;
    }
    case ParquetType::kDouble: {
      const uint8_t* p = fixed(8);
      for (int64_t i = 0; i < n; ++i) {
        double v;
        std::memcpy(&v, p + 8 * i, 8);
        d.reals.push_back(v);
      }
      return;
    }
    case ParquetType::kByteArray: {
      for (int64_t i = 0; i < n; ++i) {
        const uint32_t len = c.u32le();
        const uint8_t* p = c.take(len, "BYTE_ARRAY value");
        d.strings.emplace_back(reinterpret_cast<const char*>(p), len);
      }
      return;
    }
    case ParquetType::kInt96:
    case ParquetType::kFixedLenByteArray: {
      const size_t size = leaf.type == ParquetType::kInt96 ? 12 : static_cast<size_t>(leaf.type_length);
      if (size == 0) c.fail("FIXED_LEN_BYTE_ARRAY of length 0");
      const uint8_t* p = fixed(size);
      for (int64_t i = 0; i < n; ++i)
        d.strings.emplace_back(reinterpret_cast<const char*>(p + i * size), size);
      return;
    }
  }
}

// Appends dictionary entries `indices` to `d`.
void append_from_dictionary(Cursor& c, const Decoded& dict, const std::vector<uint32_t>& indices, Decoded& d,
                            int64_t max_bytes) {
  const size_t size = dict.value_count();
  for (uint32_t i : indices) {
    if (i >= size)
      c.fail("dictionary index " + std::to_string(i) + " >= dictionary size " + std::to_string(size));
    // Repeating a long dictionary string must not blow up memory.
    if (!dict.strings.empty()) {
      d.string_bytes += static_cast<int64_t>(dict.strings[i].size());
      if (d.string_bytes > max_bytes)
        c.fail("decoded strings exceed " + std::to_string(max_bytes) + " bytes");
    }
  }
  if (!dict.ints.empty())
    for (uint32_t i : indices) d.ints.push_back(dict.ints[i]);
  else if (!dict.reals.empty())
    for (uint32_t i : indices) d.reals.push_back(dict.reals[i]);
  else
    for (uint32_t i : indices) d.strings.push_back(dict.strings[i]);
}

}  // namespace

struct ParquetFile::Impl {
  std::string name;
  std::string bytes;
  ParquetLimits limits;
  ParquetField root;
  std::vector<Leaf> leaves;
  std::vector<RowGroup> row_groups;
  int64_t num_rows = 0;

  [[noreturn]] void fail(const std::string& what) const { throw Error(name + ": " + what); }

  void build_schema(const std::vector<SchemaElement>& elements);
  void add_field(const std::vector<SchemaElement>& elements, size_t& next, ParquetField& field, int depth,
                 std::vector<std::string> path, int def, int rep, size_t top);
  std::string decompress(const uint8_t* data, size_t size, int codec, int64_t expected,
                         const std::string& where) const;
  void decode_chunk(const Leaf& leaf, const ColumnChunk& chunk, Decoded& d, const std::string& where) const;
  Decoded decode_leaf(size_t leaf_index) const;
  const ParquetField& top_field(const std::string& column, size_t* index) const;
  size_t scalar_leaf(const std::string& column) const;
  size_t list_leaf(const std::string& column) const;
};

void ParquetFile::Impl::add_field(const std::vector<SchemaElement>& elements, size_t& next,
                                  ParquetField& field, int depth, std::vector<std::string> path, int def,
                                  int rep, size_t top) {
  if (depth > limits.max_schema_depth)
    fail("schema nested deeper than " + std::to_string(limits.max_schema_depth));
  if (next >= elements.size()) fail("schema ends early");
  const SchemaElement& e = elements[next++];
  field.name = e.name;
  field.repetition = e.repetition;
  field.converted_type = e.converted_type;
  if (e.repetition < 0 || e.repetition > 2) fail("schema field '" + e.name + "' has a bad repetition type");
  if (e.repetition == 1) ++def;
  if (e.repetition == 2) ++def, ++rep;
  path.push_back(e.name);
  if (e.num_children <= 0) {
    if (e.type < 0 || e.type > 7) fail("schema leaf '" + e.name + "' has no valid physical type");
    field.is_leaf = true;
    field.type = static_cast<ParquetType>(e.type);
    field.type_length = e.type_length;
    if (field.type == ParquetType::kFixedLenByteArray && e.type_length <= 0)
      fail("schema leaf '" + e.name + "' is FIXED_LEN_BYTE_ARRAY without a length");
    Leaf leaf;
    leaf.path = path;
    leaf.type = field.type;
    leaf.type_length = e.type_length;
    leaf.max_def = def;
    leaf.max_rep = rep;
    leaf.optional = e.repetition == 1;
    leaf.top = top;
    leaves.push_back(leaf);
    return;
  }
  if (static_cast<size_t>(e.num_children) > elements.size() - next)
    fail("schema field '" + e.name + "' claims more children than the schema holds");
  field.children.resize(static_cast<size_t>(e.num_children));
  for (auto& child : field.children) add_field(elements, next, child, depth + 1, path, def, rep, top);
}

void ParquetFile::Impl::build_schema(const std::vector<SchemaElement>& elements) {
  if (elements.empty()) fail("footer has an empty schema");
  const SchemaElement& r = elements[0];
  root.name = r.name;
  if (r.num_children < 0 || static_cast<size_t>(r.num_children) > elements.size() - 1)
    fail("schema root claims more children than the schema holds");
  root.children.resize(static_cast<size_t>(r.num_children));
  size_t next = 1;
  for (size_t i = 0; i < root.children.size(); ++i)
    add_field(elements, next, root.children[i], 1, {}, 0, 0, i);
  if (next != elements.size()) fail("schema has elements outside the tree");
}

std::string ParquetFile::Impl::decompress(const uint8_t* data, size_t size, int codec, int64_t expected,
                                          const std::string& where) const {
  if (expected < 0 || expected > limits.max_page_bytes)
    fail(where + ": page size " + std::to_string(expected) + " out of range");
  std::string out;
  switch (codec) {
    case kUncompressed:
      if (static_cast<int64_t>(size) != expected) fail(where + ": uncompressed page size mismatch");
      out.assign(reinterpret_cast<const char*>(data), size);
      return out;
    case kSnappy: {
      size_t length = 0;
      if (snappy_uncompressed_length(reinterpret_cast<const char*>(data), size, &length) != SNAPPY_OK ||
          static_cast<int64_t>(length) != expected)
        fail(where + ": corrupt snappy page");
      out.resize(length);
      if (snappy_uncompress(reinterpret_cast<const char*>(data), size, out.data(), &length) != SNAPPY_OK ||
          static_cast<int64_t>(length) != expected)
        fail(where + ": corrupt snappy page");
      return out;
    }
    case kZstd: {
      out.resize(static_cast<size_t>(expected));
      const size_t got = ZSTD_decompress(out.data(), out.size(), data, size);
      if (ZSTD_isError(got) || static_cast<int64_t>(got) != expected) fail(where + ": corrupt zstd page");
      return out;
    }
    default:
      fail(where + ": compression codec " + std::to_string(codec) +
           " not supported (only uncompressed, snappy and zstd)");
  }
}

void ParquetFile::Impl::decode_chunk(const Leaf& leaf, const ColumnChunk& chunk, Decoded& d,
                                     const std::string& where) const {
  if (!chunk.has_meta) fail(where + ": column chunk without metadata");
  if (!chunk.file_path.empty())
    fail(where + ": column data in another file ('" + chunk.file_path + "') is not supported");
  const ColumnMeta& m = chunk.meta;
  if (m.type != static_cast<int>(leaf.type)) fail(where + ": column chunk type differs from the schema");
  const int64_t footer_start = static_cast<int64_t>(bytes.size()) - 8;
  int64_t start = m.data_page_offset;
  if (m.dictionary_page_offset > 0 && m.dictionary_page_offset < start) start = m.dictionary_page_offset;
  if (start < 4 || m.total_compressed_size < 0 || m.total_compressed_size > footer_start - start)
    fail(where + ": column chunk lies outside the file");
  if (m.num_values < 0 || m.num_values > limits.max_column_values - d.entries)
    fail(where + ": column chunk value count " + std::to_string(m.num_values) + " out of range");
  Cursor c(reinterpret_cast<const uint8_t*>(bytes.data()) + start,
           static_cast<size_t>(m.total_compressed_size), &name);

  const int def_width = bit_width(leaf.max_def);
  const int rep_width = bit_width(leaf.max_rep);
  Decoded dict;
  bool have_dict = false;
  int64_t seen = 0;
  while (seen < m.num_values) {
    if (c.remaining() == 0)
      fail(where + ": column chunk ends after " + std::to_string(seen) + " of " +
           std::to_string(m.num_values) + " values");
    Compact p(c);
    const PageHeader h = read_page_header(p);
    if (h.compressed_size < 0 || h.uncompressed_size < 0) fail(where + ": page header without sizes");
    const uint8_t* payload = c.take(static_cast<size_t>(h.compressed_size), "page data");
    if (h.type == kDictionaryPage) {
      if (!h.has_dict) fail(where + ": dictionary page without its header");
      if (have_dict) fail(where + ": second dictionary page in one column chunk");
      if (h.encoding != kPlain && h.encoding != kPlainDictionary)
        fail(where + ": dictionary page not PLAIN encoded");
      if (h.num_values < 0) fail(where + ": negative dictionary size");
      const std::string page =
          decompress(payload, static_cast<size_t>(h.compressed_size), m.codec, h.uncompressed_size, where);
      Cursor v(reinterpret_cast<const uint8_t*>(page.data()), page.size(), &name);
      decode_plain(v, leaf, h.num_values, dict);
      have_dict = true;
      continue;
    }
    if (h.type != kDataPage && h.type != kDataPageV2) continue;  // index pages: nothing to decode
    if ((h.type == kDataPage && !h.has_data) || (h.type == kDataPageV2 && !h.has_v2))
      fail(where + ": data page without its header");
    if (h.num_values < 0 || h.num_values > m.num_values - seen)
      fail(where + ": page value count " + std::to_string(h.num_values) + " exceeds the column chunk's");
    const int64_t n = h.num_values;

    // Levels and the values section, decompressed as the page version requires.
    std::string page;
    const uint8_t* values_begin = nullptr;
    size_t values_size = 0;
    std::string values_buffer;
    if (h.type == kDataPage) {
      page = decompress(payload, static_cast<size_t>(h.compressed_size), m.codec, h.uncompressed_size, where);
      Cursor pc(reinterpret_cast<const uint8_t*>(page.data()), page.size(), &name);
      auto level_block = [&](int max_level, int encoding, std::vector<uint8_t>& out, int width,
                             const char* what) {
        if (max_level == 0) return;
        if (encoding != kRle)
          fail(where + ": " + what + " encoding " + std::to_string(encoding) + " not supported (only RLE)");
        const uint32_t len = pc.u32le();
        Cursor lc(pc.take(len, what), len, &name);
        decode_hybrid(lc, width, n, out, what);
      };
      level_block(leaf.max_rep, h.rep_encoding, d.rep, rep_width, "repetition levels");
      level_block(leaf.max_def, h.def_encoding, d.def, def_width, "definition levels");
      values_begin = pc.here();
      values_size = pc.remaining();
    } else {
      if (h.def_length < 0 || h.rep_length < 0 ||
          static_cast<int64_t>(h.def_length) + h.rep_length > h.compressed_size ||
          static_cast<int64_t>(h.def_length) + h.rep_length > h.uncompressed_size)
        fail(where + ": V2 page level lengths out of range");
      Cursor pc(payload, static_cast<size_t>(h.compressed_size), &name);
      if (leaf.max_rep > 0) {
        Cursor lc(pc.take(static_cast<size_t>(h.rep_length), "repetition levels"),
                  static_cast<size_t>(h.rep_length), &name);
        decode_hybrid(lc, rep_width, n, d.rep, "repetition levels");
      } else {
        pc.take(static_cast<size_t>(h.rep_length), "repetition levels");
      }
      if (leaf.max_def > 0) {
        Cursor lc(pc.take(static_cast<size_t>(h.def_length), "definition levels"),
                  static_cast<size_t>(h.def_length), &name);
        decode_hybrid(lc, def_width, n, d.def, "definition levels");
      } else {
        pc.take(static_cast<size_t>(h.def_length), "definition levels");
      }
      const int64_t rest_expected = static_cast<int64_t>(h.uncompressed_size) - h.def_length - h.rep_length;
      if (h.is_compressed && m.codec != kUncompressed) {
        values_buffer = decompress(pc.here(), pc.remaining(), m.codec, rest_expected, where);
        values_begin = reinterpret_cast<const uint8_t*>(values_buffer.data());
        values_size = values_buffer.size();
      } else {
        if (static_cast<int64_t>(pc.remaining()) != rest_expected) fail(where + ": V2 page size mismatch");
        values_begin = pc.here();
        values_size = pc.remaining();
      }
    }

    // Non-null values of this page: entries whose definition level is the maximum.
    int64_t present = n;
    if (leaf.max_def > 0) {
      present = 0;
      for (size_t i = d.def.size() - static_cast<size_t>(n); i < d.def.size(); ++i) {
        if (d.def[i] > leaf.max_def) fail(where + ": definition level above the maximum");
        if (d.def[i] == leaf.max_def) ++present;
      }
    }
    if (leaf.max_rep > 0)
      for (size_t i = d.rep.size() - static_cast<size_t>(n); i < d.rep.size(); ++i)
        if (d.rep[i] > leaf.max_rep) fail(where + ": repetition level above the maximum");

    Cursor vc(values_begin, values_size, &name);
    if (h.encoding == kPlain) {
      decode_plain(vc, leaf, present, d);
    } else if (h.encoding == kPlainDictionary || h.encoding == kRleDictionary) {
      if (!have_dict) fail(where + ": dictionary-encoded page without a dictionary page");
      std::vector<uint32_t> indices;
      if (present > 0) {
        const int width = vc.byte();
        decode_hybrid(vc, width, present, indices, "dictionary indices");
      }
      append_from_dictionary(vc, dict, indices, d, limits.max_page_bytes * 4);
    } else {
      fail(where + ": value encoding " + std::to_string(h.encoding) +
           " not supported (only PLAIN and dictionary)");
    }
    d.entries += n;
    seen += n;
  }
}

Decoded ParquetFile::Impl::decode_leaf(size_t leaf_index) const {
  const Leaf& leaf = leaves[leaf_index];
  std::string column;
  for (const auto& part : leaf.path) column += (column.empty() ? "" : ".") + part;
  Decoded d;
  for (size_t g = 0; g < row_groups.size(); ++g) {
    const std::string where = "column '" + column + "' (row group " + std::to_string(g) + ")";
    decode_chunk(leaf, row_groups[g].columns[leaf_index], d, where);
  }
  return d;
}

const ParquetField& ParquetFile::Impl::top_field(const std::string& column, size_t* index) const {
  for (size_t i = 0; i < root.children.size(); ++i)
    if (root.children[i].name == column) {
      if (index) *index = i;
      return root.children[i];
    }
  fail("no column '" + column + "'");
}

size_t ParquetFile::Impl::scalar_leaf(const std::string& column) const {
  size_t top = 0;
  const ParquetField& f = top_field(column, &top);
  if (!f.is_leaf || f.repetition == 2) fail("column '" + column + "' is not a scalar column");
  for (size_t i = 0; i < leaves.size(); ++i)
    if (leaves[i].top == top) return i;
  fail("column '" + column + "' has no data");
}

size_t ParquetFile::Impl::list_leaf(const std::string& column) const {
  size_t top = 0;
  const ParquetField& f = top_field(column, &top);
  // 3-level: <field> (LIST) { repeated group list { element } }; 2-level: <field> { repeated element }.
  bool ok =
      !f.is_leaf && f.repetition != 2 && f.children.size() == 1 && f.children[0].repetition == 2 &&
      (f.children[0].is_leaf || (f.children[0].children.size() == 1 && f.children[0].children[0].is_leaf));
  if (!ok) fail("column '" + column + "' is not a list column");
  for (size_t i = 0; i < leaves.size(); ++i)
    if (leaves[i].top == top && leaves[i].max_rep == 1) return i;
  fail("column '" + column + "' is not a list column");
}

ParquetFile::ParquetFile() = default;
ParquetFile::~ParquetFile() = default;
ParquetFile::ParquetFile(ParquetFile&&) noexcept = default;
ParquetFile& ParquetFile::operator=(ParquetFile&&) noexcept = default;

ParquetFile ParquetFile::open(const std::filesystem::path& path, ParquetLimits limits) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) throw Error(path.string() + ": file not found");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path.string() + ": cannot open");
  in.seekg(0, std::ios::end);
  const std::streamoff size = in.tellg();
  if (size < 0 || size > limits.max_file_bytes) throw Error(path.string() + ": file too large or unreadable");
  in.seekg(0);
  std::string bytes(static_cast<size_t>(size), '\0');
  in.read(bytes.data(), size);
  if (!in) throw Error(path.string() + ": read failed");
  return from_buffer(std::move(bytes), path.string(), limits);
}

ParquetFile ParquetFile::from_buffer(std::string bytes, const std::string& name, ParquetLimits limits) {
  ParquetFile file;
  file.impl_ = std::make_unique<Impl>();
  Impl& im = *file.impl_;
  im.name = name;
  im.limits = limits;
  im.bytes = std::move(bytes);
  const std::string& b = im.bytes;
  if (b.size() < 12 || b.compare(0, 4, "PAR1") != 0 || b.compare(b.size() - 4, 4, "PAR1") != 0)
    im.fail("not a parquet file (missing PAR1 magic; truncated?)");
  uint32_t footer_len = 0;
  std::memcpy(&footer_len, b.data() + b.size() - 8, 4);  // little-endian hosts only (x86, arm)
  if (footer_len == 0 || footer_len > b.size() - 12) im.fail("footer length out of range (truncated file?)");
  const size_t footer_start = b.size() - 8 - footer_len;
  Cursor c(reinterpret_cast<const uint8_t*>(b.data()) + footer_start, footer_len, &im.name);
  Compact p(c);
  std::vector<SchemaElement> schema;
  bool has_rows = false;
  p.read_struct(0, [&](int16_t id, int type) {
    switch (id) {
      case 2: {
        p.expect(type, kList, "FileMetaData.schema");
        const auto [elem, size] = p.list_header();
        if (elem != kStruct) c.fail("FileMetaData.schema is not a struct list");
        for (uint64_t i = 0; i < size; ++i) schema.push_back(read_schema_element(p, 1));
        return true;
      }
      case 3:
        p.expect(type, kI64, "FileMetaData.num_rows"), im.num_rows = p.i64(), has_rows = true;
        return true;
      case 4: {
        p.expect(type, kList, "FileMetaData.row_groups");
        const auto [elem, size] = p.list_header();
        if (elem != kStruct) c.fail("FileMetaData.row_groups is not a struct list");
        for (uint64_t i = 0; i < size; ++i) im.row_groups.push_back(read_row_group(p, 1));
        return true;
      }
      default:
        return false;
    }
  });
  if (!has_rows || im.num_rows < 0) im.fail("footer has no valid num_rows");
  im.build_schema(schema);
  int64_t rows = 0;
  for (size_t g = 0; g < im.row_groups.size(); ++g) {
    const auto& group = im.row_groups[g];
    if (group.columns.size() != im.leaves.size())
      im.fail("row group " + std::to_string(g) + " has " + std::to_string(group.columns.size()) +
              " column chunks for " + std::to_string(im.leaves.size()) + " schema leaves");
    if (group.num_rows < 0 || group.num_rows > im.num_rows - rows)
      im.fail("row group row counts exceed num_rows");
    rows += group.num_rows;
  }
  if (rows != im.num_rows)
    im.fail("row groups hold " + std::to_string(rows) + " rows, footer says " + std::to_string(im.num_rows));
  return file;
}

const std::string& ParquetFile::name() const { return impl_->name; }
int64_t ParquetFile::num_rows() const { return impl_->num_rows; }
int64_t ParquetFile::num_row_groups() const { return static_cast<int64_t>(impl_->row_groups.size()); }
const ParquetField& ParquetFile::schema() const { return impl_->root; }

bool ParquetFile::has_column(const std::string& name) const {
  for (const auto& f : impl_->root.children)
    if (f.name == name) return true;
  return false;
}

std::vector<ParquetColumnInfo> ParquetFile::columns() const {
  std::vector<ParquetColumnInfo> out;
  for (const auto& f : impl_->root.children) {
    ParquetColumnInfo info;
    info.name = f.name;
    info.optional = f.repetition == 1;
    if (f.is_leaf) {
      info.kind = to_string(f.type);
      if (f.repetition == 2) info.kind = "list<" + info.kind + ">";
    } else if (f.children.size() == 1 && f.children[0].repetition == 2) {
      const ParquetField& inner = f.children[0];
      if (inner.is_leaf)
        info.kind = "list<" + to_string(inner.type) + ">";
      else if (inner.children.size() == 1 && inner.children[0].is_leaf)
        info.kind = "list<" + to_string(inner.children[0].type) + ">";
      else
        info.kind = "list<struct>";
    } else {
      info.kind = "struct";
    }
    out.push_back(info);
  }
  return out;
}

namespace {

// Checks a scalar column's levels: no repetition, no nulls.
void check_scalar(const ParquetFile::Impl& im, const Leaf& leaf, const Decoded& d,
                  const std::string& column) {
  if (d.entries != im.num_rows)
    im.fail("column '" + column + "' has " + std::to_string(d.entries) + " values for " +
            std::to_string(im.num_rows) + " rows");
  if (leaf.max_def > 0)
    for (size_t r = 0; r < d.def.size(); ++r)
      if (d.def[r] != leaf.max_def) im.fail("column '" + column + "' is null at row " + std::to_string(r));
}

std::string kind_of(const Leaf& leaf) { return to_string(leaf.type); }

bool is_int(ParquetType t) {
  return t == ParquetType::kInt32 || t == ParquetType::kInt64 || t == ParquetType::kBoolean;
}
bool is_real(ParquetType t) { return t == ParquetType::kFloat || t == ParquetType::kDouble; }
bool is_bytes(ParquetType t) { return t == ParquetType::kByteArray || t == ParquetType::kFixedLenByteArray; }

// Row offsets of a list column from its levels.
std::vector<int64_t> list_offsets(const ParquetFile::Impl& im, const Leaf& leaf, const Decoded& d,
                                  const std::string& column) {
  std::vector<int64_t> offsets;
  int64_t values = 0;
  for (size_t i = 0; i < d.rep.size(); ++i) {
    if (d.rep[i] == 0)
      offsets.push_back(values);
    else if (offsets.empty())
      im.fail("column '" + column + "' starts with a continued list");
    if (d.def[i] == leaf.max_def)
      ++values;
    else if (leaf.optional && d.def[i] == leaf.max_def - 1)
      im.fail("column '" + column + "' has a null list element in row " + std::to_string(offsets.size() - 1));
  }
  offsets.push_back(values);
  if (static_cast<int64_t>(offsets.size()) - 1 != im.num_rows)
    im.fail("column '" + column + "' holds " + std::to_string(offsets.size() - 1) + " lists for " +
            std::to_string(im.num_rows) + " rows");
  return offsets;
}

}  // namespace

std::vector<int64_t> ParquetFile::read_i64(const std::string& column) const {
  const size_t li = impl_->scalar_leaf(column);
  const Leaf& leaf = impl_->leaves[li];
  if (!is_int(leaf.type))
    impl_->fail("column '" + column + "' is " + kind_of(leaf) + ", expected an integer");
  Decoded d = impl_->decode_leaf(li);
  check_scalar(*impl_, leaf, d, column);
  return std::move(d.ints);
}

std::vector<double> ParquetFile::read_f64(const std::string& column) const {
  const size_t li = impl_->scalar_leaf(column);
  const Leaf& leaf = impl_->leaves[li];
  if (!is_real(leaf.type) && !is_int(leaf.type))
    impl_->fail("column '" + column + "' is " + kind_of(leaf) + ", expected a number");
  Decoded d = impl_->decode_leaf(li);
  check_scalar(*impl_, leaf, d, column);
  if (is_int(leaf.type)) return std::vector<double>(d.ints.begin(), d.ints.end());
  return std::move(d.reals);
}

std::vector<float> ParquetFile::read_f32(const std::string& column) const {
  const auto v = read_f64(column);
  return std::vector<float>(v.begin(), v.end());
}

std::vector<std::string> ParquetFile::read_string(const std::string& column) const {
  const size_t li = impl_->scalar_leaf(column);
  const Leaf& leaf = impl_->leaves[li];
  if (!is_bytes(leaf.type)) impl_->fail("column '" + column + "' is " + kind_of(leaf) + ", expected string");
  Decoded d = impl_->decode_leaf(li);
  check_scalar(*impl_, leaf, d, column);
  return std::move(d.strings);
}

ParquetList<double> ParquetFile::read_list_f64(const std::string& column) const {
  const size_t li = impl_->list_leaf(column);
  const Leaf& leaf = impl_->leaves[li];
  if (!is_real(leaf.type) && !is_int(leaf.type))
    impl_->fail("column '" + column + "' is list<" + kind_of(leaf) + ">, expected a list of numbers");
  Decoded d = impl_->decode_leaf(li);
  ParquetList<double> out;
  out.offsets = list_offsets(*impl_, leaf, d, column);
  if (is_int(leaf.type))
    out.values.assign(d.ints.begin(), d.ints.end());
  else
    out.values = std::move(d.reals);
  return out;
}

ParquetList<float> ParquetFile::read_list_f32(const std::string& column) const {
  auto l = read_list_f64(column);
  ParquetList<float> out;
  out.values.assign(l.values.begin(), l.values.end());
  out.offsets = std::move(l.offsets);
  return out;
}

ParquetList<std::string> ParquetFile::read_list_string(const std::string& column) const {
  const size_t li = impl_->list_leaf(column);
  const Leaf& leaf = impl_->leaves[li];
  if (!is_bytes(leaf.type))
    impl_->fail("column '" + column + "' is list<" + kind_of(leaf) + ">, expected list<string>");
  Decoded d = impl_->decode_leaf(li);
  ParquetList<std::string> out;
  out.offsets = list_offsets(*impl_, leaf, d, column);
  out.values = std::move(d.strings);
  return out;
}

int64_t ParquetFile::decode_all() const {
  int64_t total = 0;
  for (size_t i = 0; i < impl_->leaves.size(); ++i) total += impl_->decode_leaf(i).entries;
  return total;
}

}  // namespace dojo::io
