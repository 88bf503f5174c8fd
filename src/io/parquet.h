// A small Parquet reader for what LeRobot datasets contain. Debian 12 packages no Parquet
// library (no Arrow, no DuckDB), so this decodes the subset itself:
//   footer:    Thrift compact protocol; FileMetaData, SchemaElement, RowGroup, ColumnChunk,
//              ColumnMetaData, PageHeader with DataPageHeader (V1), DataPageHeaderV2 and
//              DictionaryPageHeader (other fields are skipped)
//   types:     BOOLEAN, INT32, INT64, FLOAT, DOUBLE, BYTE_ARRAY, FIXED_LEN_BYTE_ARRAY
//   encodings: PLAIN, PLAIN_DICTIONARY / RLE_DICTIONARY, RLE/bit-packed hybrid levels
//   codecs:    UNCOMPRESSED, SNAPPY, ZSTD
//   nesting:   required and optional top-level columns; list<T> columns (the 3-level LIST
//              layout Arrow writes, and the legacy 2-level `repeated` one)
// Everything read from the file is bounds-checked: malformed or hostile input throws
// dojo::Error naming the file (and the column), never reads out of bounds (fuzzed with
// libFuzzer + ASan/UBSan, see fuzz/parquet_fuzz.cpp). Torch-free so the fuzzer builds alone.
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

namespace dojo::io {

enum class ParquetType {
  kBoolean = 0,
  kInt32 = 1,
  kInt64 = 2,
  kInt96 = 3,
  kFloat = 4,
  kDouble = 5,
  kByteArray = 6,
  kFixedLenByteArray = 7
};
std::string to_string(ParquetType type);

// One field of the schema tree. Leaves carry a physical type; groups carry children.
struct ParquetField {
  std::string name;
  int repetition = 0;  // 0 required, 1 optional, 2 repeated
  bool is_leaf = false;
  ParquetType type = ParquetType::kInt32;
  int type_length = 0;      // FIXED_LEN_BYTE_ARRAY width
  int converted_type = -1;  // legacy annotation (0 UTF8, 3 LIST, ...); -1 when absent
  std::vector<ParquetField> children;
};

// A top-level column as seen by users of the reader.
struct ParquetColumnInfo {
  std::string name;
  std::string kind;  // "int32", "int64", "float", "double", "bool", "string", "list<float>", "struct", ...
  bool optional = false;
};

// Caps on what a file may make the reader allocate, so that a corrupt header cannot ask for
// gigabytes. Defaults fit any LeRobot file; the fuzzer lowers them.
struct ParquetLimits {
  int64_t max_file_bytes = int64_t(4) << 30;
  int64_t max_page_bytes = int64_t(512) << 20;   // one uncompressed page
  int64_t max_column_values = int64_t(1) << 28;  // decoded level entries of one column
  int max_schema_depth = 16;
};

// list<T> column: row r holds values[offsets[r] .. offsets[r + 1]).
template <typename T>
struct ParquetList {
  std::vector<T> values;
  std::vector<int64_t> offsets;  // num_rows + 1 entries
  int64_t rows() const { return offsets.empty() ? 0 : static_cast<int64_t>(offsets.size()) - 1; }
};

class ParquetFile {
 public:
  // Reads the whole file (LeRobot files are at most a few hundred MB) and decodes the footer.
  // Throws dojo::Error "PATH: ..." for a missing, truncated or malformed file.
  static ParquetFile open(const std::filesystem::path& path, ParquetLimits limits = {});
  // Same from bytes in memory; `name` stands in for the path in error messages.
  static ParquetFile from_buffer(std::string bytes, const std::string& name, ParquetLimits limits = {});

  ParquetFile();
  ~ParquetFile();
  ParquetFile(ParquetFile&&) noexcept;
  ParquetFile& operator=(ParquetFile&&) noexcept;

  const std::string& name() const;
  int64_t num_rows() const;
  int64_t num_row_groups() const;
  const ParquetField& schema() const;  // the root group
  std::vector<ParquetColumnInfo> columns() const;
  bool has_column(const std::string& name) const;

  // Scalar columns, one entry per row. Integer readers accept INT32/INT64/BOOLEAN, float
  // readers FLOAT/DOUBLE (and integers, converted). A missing column, a wrong type, a list
  // column or a null value throws dojo::Error naming the file and the column.
  std::vector<int64_t> read_i64(const std::string& column) const;
  std::vector<double> read_f64(const std::string& column) const;
  std::vector<float> read_f32(const std::string& column) const;
  std::vector<std::string> read_string(const std::string& column) const;

  // list<number> and list<string> columns. A null list reads as empty; a null element throws.
  ParquetList<float> read_list_f32(const std::string& column) const;
  ParquetList<double> read_list_f64(const std::string& column) const;
  ParquetList<std::string> read_list_string(const std::string& column) const;

  // Decodes every leaf column without interpreting it (what the fuzzer exercises). Returns the
  // number of level entries decoded.
  int64_t decode_all() const;

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace dojo::io
