// Internal to src/io (not a public header): what decoding a column yields (Leaf, Decoded) and
// ParquetFile::Impl, the reader's state. Impl's schema and lookup members are defined in
// parquet.cpp, its page decoding (decompress, decode_chunk, decode_leaf) in parquet_decode.cpp.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "core/error.h"
#include "io/parquet.h"
#include "io/parquet_thrift.h"

namespace dojo::io {

namespace parquet_detail {

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

}  // namespace parquet_detail

// The reader's state; ParquetFile holds it behind a pointer.
struct ParquetFile::Impl {
  std::string name;
  std::string bytes;
  ParquetLimits limits;
  ParquetField root;
  std::vector<parquet_detail::Leaf> leaves;
  std::vector<parquet_detail::RowGroup> row_groups;
  int64_t num_rows = 0;

  [[noreturn]] void fail(const std::string& what) const { throw Error(name + ": " + what); }

  void build_schema(const std::vector<parquet_detail::SchemaElement>& elements);
  void add_field(const std::vector<parquet_detail::SchemaElement>& elements, size_t& next,
                 ParquetField& field, int depth, std::vector<std::string> path, int def, int rep, size_t top);
  std::string decompress(const uint8_t* data, size_t size, int codec, int64_t expected,
                         const std::string& where) const;
  void decode_chunk(const parquet_detail::Leaf& leaf, const parquet_detail::ColumnChunk& chunk,
                    parquet_detail::Decoded& d, const std::string& where) const;
  parquet_detail::Decoded decode_leaf(size_t leaf_index) const;
  const ParquetField& top_field(const std::string& column, size_t* index) const;
  size_t scalar_leaf(const std::string& column) const;
  size_t list_leaf(const std::string& column) const;
};

}  // namespace dojo::io
