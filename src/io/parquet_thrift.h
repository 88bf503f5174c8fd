// Internal to src/io (not a public header): the Thrift compact-protocol reader and the Parquet
// footer and page-header structs the reader decodes (FileMetaData's schema, row groups, column
// chunks; PageHeader). Used by parquet.cpp and parquet_decode.cpp.
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include "core/error.h"

namespace dojo::io::parquet_detail {

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

inline int64_t zigzag(uint64_t v) { return static_cast<int64_t>(v >> 1) ^ -static_cast<int64_t>(v & 1); }

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

SchemaElement read_schema_element(Compact& p, int depth);
ColumnMeta read_column_meta(Compact& p, int depth);
ColumnChunk read_column_chunk(Compact& p, int depth);
RowGroup read_row_group(Compact& p, int depth);
PageHeader read_page_header(Compact& p);

}  // namespace dojo::io::parquet_detail
