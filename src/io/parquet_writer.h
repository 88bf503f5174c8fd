// A Parquet WRITER used as a fixture generator: the tests build their LeRobot datasets with it
// (so the suite needs nothing downloaded), the fuzzer seeds its corpus with it, and
// `dojo data` uses none of it. It writes the layout pyarrow writes for LeRobot tables:
//   scalar columns   required (or optional, with nulls) INT32/INT64/FLOAT/DOUBLE/BOOLEAN/BYTE_ARRAY
//   list columns     optional group <name> (LIST) { repeated group list { optional <T> element } }
//   pages            PLAIN or dictionary (PLAIN_DICTIONARY in V1, RLE_DICTIONARY in V2),
//                    data page V1 or V2, uncompressed / snappy / zstd
//   levels           RLE/bit-packed hybrid (long repeats as RLE runs, the rest bit-packed)
// Files it writes were cross-checked with an independent reader (hyparquet, see docs/data.md).
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "io/parquet.h"

namespace dojo::io {

enum class ParquetCodec { kUncompressed = 0, kSnappy = 1, kZstd = 6 };

struct ParquetWriteOptions {
  ParquetCodec codec = ParquetCodec::kUncompressed;
  int page_version = 1;     // 1 (DataPageHeader) or 2 (DataPageHeaderV2)
  bool dictionary = false;  // dictionary-encode the columns (else PLAIN)
  int64_t rows_per_page = 1 << 20;
  int64_t rows_per_row_group = 1 << 30;
};

class ParquetWriter {
 public:
  explicit ParquetWriter(ParquetWriteOptions options = {}) : options_(options) {}

  // Every column must have the same number of rows.
  void add_i32(const std::string& name, const std::vector<int32_t>& values);
  void add_i64(const std::string& name, const std::vector<int64_t>& values);
  void add_f32(const std::string& name, const std::vector<float>& values);
  void add_f64(const std::string& name, const std::vector<double>& values);
  void add_bool(const std::string& name, const std::vector<bool>& values);
  void add_string(const std::string& name, const std::vector<std::string>& values);
  void add_optional_f64(const std::string& name, const std::vector<std::optional<double>>& values);
  void add_optional_i64(const std::string& name, const std::vector<std::optional<int64_t>>& values);
  // list<float32> / list<float64> / list<string>; std::nullopt rows are null lists.
  void add_list_f32(const std::string& name, const std::vector<std::optional<std::vector<float>>>& rows);
  void add_list_f64(const std::string& name, const std::vector<std::optional<std::vector<double>>>& rows);
  void add_list_string(const std::string& name, const std::vector<std::vector<std::string>>& rows);

  // Overrides the dictionary option for one column (call after adding it).
  void set_dictionary(const std::string& name, bool dictionary);

  std::string to_bytes() const;
  void write(const std::filesystem::path& path) const;

  struct Value {
    int64_t i = 0;
    double d = 0;
    std::string s;
  };
  struct Column {
    std::string name;
    ParquetType type = ParquetType::kInt64;
    bool list = false;
    bool optional = false;
    bool dictionary = false;
    std::vector<Value> values;         // non-null values, in order
    std::vector<int64_t> row_lengths;  // list: elements per row (-1 null); scalar: 1 or 0 (null)
  };

 private:
  void add(Column column);

  ParquetWriteOptions options_;
  std::vector<Column> columns_;
};

}  // namespace dojo::io
