#include "io/parquet_writer.h"

#include <snappy-c.h>
#include <zstd.h>

#include <algorithm>
#include <cstring>
#include <functional>
#include <map>

#include "core/atomic_file.h"
#include "core/error.h"

namespace dojo::io {

namespace {

// Thrift compact protocol output (the mirror of the reader's subset).
class CompactWriter {
 public:
  std::string out;

  void varint(uint64_t v) {
    while (v >= 0x80) {
      out.push_back(static_cast<char>((v & 0x7f) | 0x80));
      v >>= 7;
    }
    out.push_back(static_cast<char>(v));
  }
  void zigzag(int64_t v) { varint((static_cast<uint64_t>(v) << 1) ^ static_cast<uint64_t>(v >> 63)); }
  void field(int16_t id, int type) {
    const int delta = id - last_.back();
    if (delta > 0 && delta <= 15) {
      out.push_back(static_cast<char>((delta << 4) | type));
    } else {
      out.push_back(static_cast<char>(type));
      zigzag(id);
    }
    last_.back() = id;
  }
  void i32(int16_t id, int64_t v) { field(id, 5), zigzag(v); }
  void i64(int16_t id, int64_t v) { field(id, 6), zigzag(v); }
  void boolean(int16_t id, bool v) { field(id, v ? 1 : 2); }
  void binary(const std::string& s) { varint(s.size()), out += s; }
  void string(int16_t id, const std::string& s) { field(id, 8), binary(s); }
  void list_header(int elem_type, size_t size) {
    if (size < 15) {
      out.push_back(static_cast<char>((size << 4) | elem_type));
    } else {
      out.push_back(static_cast<char>(0xf0 | elem_type));
      varint(size);
    }
  }
  void list(int16_t id, int elem_type, size_t size) { field(id, 9), list_header(elem_type, size); }
  void begin_struct(int16_t id) { field(id, 12), begin(); }
  void begin() { last_.push_back(0); }  // a struct nested as a list element
  void end() {
    out.push_back(0);
    last_.pop_back();
  }

 private:
  std::vector<int16_t> last_{0};
};

void put_u32(std::string& out, uint32_t v) {
  for (int i = 0; i < 4; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xff));
}

int bit_width(uint64_t max_value) {
  int w = 0;
  while (w < 64 && (1ull << w) <= max_value) ++w;
  return w;
}

// RLE/bit-packed hybrid: runs of 8+ equal values as RLE runs, everything else bit-packed in
// groups of 8 (the last group zero-padded).
std::string encode_hybrid(const std::vector<uint32_t>& v, int width) {
  CompactWriter w;
  std::vector<uint32_t> literal;
  auto flush_literal = [&] {
    if (literal.empty()) return;
    const size_t groups = (literal.size() + 7) / 8;
    literal.resize(groups * 8, 0);
    w.varint((groups << 1) | 1);
    std::string bits(groups * static_cast<size_t>(width), '\0');
    size_t bit = 0;
    for (uint32_t x : literal)
      for (int b = 0; b < width; ++b, ++bit)
        if ((x >> b) & 1) bits[bit >> 3] = static_cast<char>(bits[bit >> 3] | (1 << (bit & 7)));
    w.out += bits;
    literal.clear();
  };
  size_t i = 0;
  while (i < v.size()) {
    size_t j = i;
    while (j < v.size() && v[j] == v[i]) ++j;
    if (j - i >= 8) {
      // A bit-packed run in the middle of the data must hold a multiple of 8 values.
      while (literal.size() % 8 != 0 && i < j) literal.push_back(v[i++]);
      flush_literal();
      if (j > i) {
        w.varint(static_cast<uint64_t>(j - i) << 1);
        const int bytes = (width + 7) / 8;
        for (int b = 0; b < bytes; ++b) w.out.push_back(static_cast<char>((v[i] >> (8 * b)) & 0xff));
      }
    } else {
      literal.insert(literal.end(), v.begin() + static_cast<std::ptrdiff_t>(i),
                     v.begin() + static_cast<std::ptrdiff_t>(j));
    }
    i = j;
  }
  flush_literal();
  return w.out;
}

std::string encode_plain(ParquetType type, const std::vector<ParquetWriter::Value>& values) {
  std::string out;
  if (type == ParquetType::kBoolean) {
    out.assign((values.size() + 7) / 8, '\0');
    for (size_t i = 0; i < values.size(); ++i)
      if (values[i].i) out[i >> 3] = static_cast<char>(out[i >> 3] | (1 << (i & 7)));
    return out;
  }
  for (const auto& v : values) {
    switch (type) {
      case ParquetType::kInt32: {
        const int32_t x = static_cast<int32_t>(v.i);
        out.append(reinterpret_cast<const char*>(&x), 4);
        break;
      }
      case ParquetType::kInt64:
        out.append(reinterpret_cast<const char*>(&v.i), 8);
        break;
      case ParquetType::kFloat: {
        const float x = static_cast<float>(v.d);
        out.append(reinterpret_cast<const char*>(&x), 4);
        break;
      }
      case ParquetType::kDouble:
        out.append(reinterpret_cast<const char*>(&v.d), 8);
        break;
      case ParquetType::kByteArray:
        put_u32(out, static_cast<uint32_t>(v.s.size()));
        out += v.s;
        break;
      default:
        throw Error("parquet writer: unsupported type " + to_string(type));
    }
  }
  return out;
}

std::string compress(const std::string& raw, ParquetCodec codec) {
  switch (codec) {
    case ParquetCodec::kUncompressed:
      return raw;
    case ParquetCodec::kSnappy: {
      size_t length = snappy_max_compressed_length(raw.size());
      std::string out(length, '\0');
      if (snappy_compress(raw.data(), raw.size(), out.data(), &length) != SNAPPY_OK)
        throw Error("parquet writer: snappy failed");
      out.resize(length);
      return out;
    }
    case ParquetCodec::kZstd: {
      std::string out(ZSTD_compressBound(raw.size()), '\0');
      const size_t n = ZSTD_compress(out.data(), out.size(), raw.data(), raw.size(), 3);
      if (ZSTD_isError(n)) throw Error("parquet writer: zstd failed");
      out.resize(n);
      return out;
    }
  }
  return raw;
}

// A column's value key for dictionary building.
std::string value_key(const ParquetWriter::Value& v) {
  return std::to_string(v.i) + "|" + std::to_string(v.d) + "|" + v.s;
}

struct ChunkResult {
  std::string bytes;
  int64_t num_values = 0;  // level entries
  int64_t uncompressed = 0;
  int64_t data_offset = 0, dict_offset = -1;  // relative to the chunk start
};

}  // namespace

namespace {
ParquetWriter::Column make_column(const std::string& name, ParquetType type) {
  ParquetWriter::Column c;
  c.name = name;
  c.type = type;
  return c;
}
}  // namespace

void ParquetWriter::add(Column column) {
  if (!columns_.empty() && columns_.front().row_lengths.size() != column.row_lengths.size())
    throw Error("parquet writer: column '" + column.name + "' has " +
                std::to_string(column.row_lengths.size()) + " rows, the others " +
                std::to_string(columns_.front().row_lengths.size()));
  // pyarrow never dictionary-encodes booleans (readers treat such pages as RLE booleans).
  column.dictionary = options_.dictionary && column.type != ParquetType::kBoolean;
  columns_.push_back(std::move(column));
}

void ParquetWriter::set_dictionary(const std::string& name, bool dictionary) {
  for (auto& c : columns_)
    if (c.name == name) c.dictionary = dictionary && c.type != ParquetType::kBoolean;
}

void ParquetWriter::add_i32(const std::string& name, const std::vector<int32_t>& values) {
  Column c = make_column(name, ParquetType::kInt32);
  for (int32_t v : values) c.values.push_back({v, 0, {}}), c.row_lengths.push_back(1);
  add(std::move(c));
}
void ParquetWriter::add_i64(const std::string& name, const std::vector<int64_t>& values) {
  Column c = make_column(name, ParquetType::kInt64);
  for (int64_t v : values) c.values.push_back({v, 0, {}}), c.row_lengths.push_back(1);
  add(std::move(c));
}
void ParquetWriter::add_f32(const std::string& name, const std::vector<float>& values) {
  Column c = make_column(name, ParquetType::kFloat);
  for (float v : values) c.values.push_back({0, v, {}}), c.row_lengths.push_back(1);
  add(std::move(c));
}
void ParquetWriter::add_f64(const std::string& name, const std::vector<double>& values) {
  Column c = make_column(name, ParquetType::kDouble);
  for (double v : values) c.values.push_back({0, v, {}}), c.row_lengths.push_back(1);
  add(std::move(c));
}
void ParquetWriter::add_bool(const std::string& name, const std::vector<bool>& values) {
  Column c = make_column(name, ParquetType::kBoolean);
  for (bool v : values) c.values.push_back({v ? 1 : 0, 0, {}}), c.row_lengths.push_back(1);
  add(std::move(c));
}
void ParquetWriter::add_string(const std::string& name, const std::vector<std::string>& values) {
  Column c = make_column(name, ParquetType::kByteArray);
  for (const auto& v : values) c.values.push_back({0, 0, v}), c.row_lengths.push_back(1);
  add(std::move(c));
}
void ParquetWriter::add_optional_f64(const std::string& name,
                                     const std::vector<std::optional<double>>& values) {
  Column c = make_column(name, ParquetType::kDouble);
  c.optional = true;
  for (const auto& v : values) {
    if (v) c.values.push_back({0, *v, {}});
    c.row_lengths.push_back(v ? 1 : 0);
  }
  add(std::move(c));
}
void ParquetWriter::add_optional_i64(const std::string& name,
                                     const std::vector<std::optional<int64_t>>& values) {
  Column c = make_column(name, ParquetType::kInt64);
  c.optional = true;
  for (const auto& v : values) {
    if (v) c.values.push_back({*v, 0, {}});
    c.row_lengths.push_back(v ? 1 : 0);
  }
  add(std::move(c));
}
void ParquetWriter::add_list_f32(const std::string& name,
                                 const std::vector<std::optional<std::vector<float>>>& rows) {
  Column c = make_column(name, ParquetType::kFloat);
  c.list = true;
  for (const auto& row : rows) {
    c.row_lengths.push_back(row ? static_cast<int64_t>(row->size()) : -1);
    if (row)
      for (float v : *row) c.values.push_back({0, v, {}});
  }
  add(std::move(c));
}
void ParquetWriter::add_list_f64(const std::string& name,
                                 const std::vector<std::optional<std::vector<double>>>& rows) {
  Column c = make_column(name, ParquetType::kDouble);
  c.list = true;
  for (const auto& row : rows) {
    c.row_lengths.push_back(row ? static_cast<int64_t>(row->size()) : -1);
    if (row)
      for (double v : *row) c.values.push_back({0, v, {}});
  }
  add(std::move(c));
}
void ParquetWriter::add_list_string(const std::string& name,
                                    const std::vector<std::vector<std::string>>& rows) {
  Column c = make_column(name, ParquetType::kByteArray);
  c.list = true;
  for (const auto& row : rows) {
    c.row_lengths.push_back(static_cast<int64_t>(row.size()));
    for (const auto& v : row) c.values.push_back({0, 0, v});
  }
  add(std::move(c));
}

namespace {

void write_page_header(std::string& out, int type, int64_t uncompressed, int64_t compressed,
                       const std::function<void(CompactWriter&)>& body) {
  CompactWriter w;
  w.i32(1, type);
  w.i32(2, uncompressed);
  w.i32(3, compressed);
  body(w);
  w.end();
  out += w.out;
}

// One column chunk: rows [row_begin, row_end) of `c`; `value_begin` is the index of the first
// value of row_begin in c.values.
ChunkResult write_chunk(const ParquetWriter::Column& c, int64_t row_begin, int64_t row_end,
                        size_t value_begin, const ParquetWriteOptions& o) {
  ChunkResult r;
  const int max_def = c.list ? 3 : (c.optional ? 1 : 0);
  const int max_rep = c.list ? 1 : 0;

  // Dictionary of the chunk's values, in first-seen order.
  std::vector<ParquetWriter::Value> dict;
  std::map<std::string, uint32_t> dict_index;
  size_t value_end = value_begin;
  for (int64_t row = row_begin; row < row_end; ++row)
    value_end += static_cast<size_t>(std::max<int64_t>(0, c.row_lengths[row]));
  std::vector<uint32_t> indices;
  if (c.dictionary) {
    for (size_t i = value_begin; i < value_end; ++i) {
      const auto key = value_key(c.values[i]);
      auto it = dict_index.find(key);
      if (it == dict_index.end()) {
        it = dict_index.emplace(key, static_cast<uint32_t>(dict.size())).first;
        dict.push_back(c.values[i]);
      }
      indices.push_back(it->second);
    }
    const std::string raw = encode_plain(c.type, dict);
    const std::string packed = compress(raw, o.codec);
    r.dict_offset = 0;
    write_page_header(r.bytes, 2, static_cast<int64_t>(raw.size()), static_cast<int64_t>(packed.size()),
                      [&](CompactWriter& w) {
                        w.begin_struct(7);
                        w.i32(1, static_cast<int64_t>(dict.size()));
                        w.i32(2, o.page_version == 1 ? 2 : 0);  // PLAIN_DICTIONARY (V1 style) or PLAIN
                        w.end();
                      });
    r.bytes += packed;
    r.uncompressed += static_cast<int64_t>(raw.size());
  }
  r.data_offset = static_cast<int64_t>(r.bytes.size());

  size_t value = value_begin;
  for (int64_t page_begin = row_begin; page_begin < row_end; page_begin += o.rows_per_page) {
    const int64_t page_end = std::min(row_end, page_begin + o.rows_per_page);
    std::vector<uint32_t> def, rep;
    std::vector<ParquetWriter::Value> values;
    std::vector<uint32_t> page_indices;
    int64_t nulls = 0;
    for (int64_t row = page_begin; row < page_end; ++row) {
      const int64_t len = c.row_lengths[row];
      if (!c.list) {
        if (max_def) def.push_back(len == 1 ? 1 : 0);
        if (len == 0) ++nulls;
      } else if (len < 0) {
        def.push_back(0), rep.push_back(0), ++nulls;
      } else if (len == 0) {
        def.push_back(1), rep.push_back(0), ++nulls;
      } else {
        for (int64_t k = 0; k < len; ++k) def.push_back(3), rep.push_back(k == 0 ? 0 : 1);
      }
      for (int64_t k = 0; k < std::max<int64_t>(0, len); ++k, ++value) {
        if (c.dictionary)
          page_indices.push_back(indices[value - value_begin]);
        else
          values.push_back(c.values[value]);
      }
    }
    const int64_t entries = c.list ? static_cast<int64_t>(def.size()) : page_end - page_begin;
    std::string rep_bytes = max_rep ? encode_hybrid(rep, bit_width(max_rep)) : "";
    std::string def_bytes = max_def ? encode_hybrid(def, bit_width(max_def)) : "";
    std::string value_bytes;
    if (c.dictionary) {
      const int width = bit_width(dict.empty() ? 0 : dict.size() - 1);
      value_bytes.push_back(static_cast<char>(width));
      value_bytes += encode_hybrid(page_indices, width);
    } else {
      value_bytes = encode_plain(c.type, values);
    }
    const int encoding = c.dictionary ? (o.page_version == 1 ? 2 : 8) : 0;
    if (o.page_version == 1) {
      std::string raw;
      if (max_rep) put_u32(raw, static_cast<uint32_t>(rep_bytes.size())), raw += rep_bytes;
      if (max_def) put_u32(raw, static_cast<uint32_t>(def_bytes.size())), raw += def_bytes;
      raw += value_bytes;
      const std::string packed = compress(raw, o.codec);
      write_page_header(r.bytes, 0, static_cast<int64_t>(raw.size()), static_cast<int64_t>(packed.size()),
                        [&](CompactWriter& w) {
                          w.begin_struct(5);
                          w.i32(1, entries);
                          w.i32(2, encoding);
                          w.i32(3, 3);  // RLE
                          w.i32(4, 3);
                          w.end();
                        });
      r.bytes += packed;
      r.uncompressed += static_cast<int64_t>(raw.size());
    } else {
      const std::string packed_values = compress(value_bytes, o.codec);
      const int64_t raw_size = static_cast<int64_t>(rep_bytes.size() + def_bytes.size() + value_bytes.size());
      const int64_t packed_size =
          static_cast<int64_t>(rep_bytes.size() + def_bytes.size() + packed_values.size());
      write_page_header(r.bytes, 3, raw_size, packed_size, [&](CompactWriter& w) {
        w.begin_struct(8);
        w.i32(1, entries);
        w.i32(2, nulls);
        w.i32(3, page_end - page_begin);
        w.i32(4, encoding);
        w.i32(5, static_cast<int64_t>(def_bytes.size()));
        w.i32(6, static_cast<int64_t>(rep_bytes.size()));
        w.boolean(7, o.codec != ParquetCodec::kUncompressed);
        w.end();
      });
      r.bytes += rep_bytes + def_bytes + packed_values;
      r.uncompressed += raw_size;
    }
    r.num_values += entries;
  }
  return r;
}

}  // namespace

std::string ParquetWriter::to_bytes() const {
  if (options_.page_version != 1 && options_.page_version != 2)
    throw Error("parquet writer: page_version must be 1 or 2");
  if (options_.rows_per_page <= 0 || options_.rows_per_row_group <= 0)
    throw Error("parquet writer: bad page/row group size");
  const int64_t rows = columns_.empty() ? 0 : static_cast<int64_t>(columns_.front().row_lengths.size());
  std::string file = "PAR1";
  struct ChunkMeta {
    ChunkResult chunk;
    int64_t offset;
  };
  std::vector<std::vector<ChunkMeta>> groups;
  std::vector<int64_t> group_rows;
  std::vector<size_t> value_pos(columns_.size(), 0);
  for (int64_t begin = 0; begin < rows || (rows == 0 && groups.empty());
       begin += options_.rows_per_row_group) {
    const int64_t end = std::min(rows, begin + options_.rows_per_row_group);
    std::vector<ChunkMeta> chunks;
    for (size_t ci = 0; ci < columns_.size(); ++ci) {
      const Column& c = columns_[ci];
      ChunkMeta m{write_chunk(c, begin, end, value_pos[ci], options_), static_cast<int64_t>(file.size())};
      for (int64_t row = begin; row < end; ++row)
        value_pos[ci] += static_cast<size_t>(std::max<int64_t>(0, c.row_lengths[row]));
      file += m.chunk.bytes;
      chunks.push_back(std::move(m));
    }
    groups.push_back(std::move(chunks));
    group_rows.push_back(end - begin);
    if (rows == 0) break;
  }

  CompactWriter w;
  w.i32(1, 1);  // version
  // Schema: the root, then each column (lists as the 3-level LIST layout).
  size_t elements = 1;
  for (const auto& c : columns_) elements += c.list ? 3 : 1;
  w.list(2, 12, elements);
  w.begin();
  w.string(4, "schema");
  w.i32(5, static_cast<int64_t>(columns_.size()));
  w.end();
  for (const auto& c : columns_) {
    if (c.list) {
      w.begin();
      w.i32(3, 1);
      w.string(4, c.name);
      w.i32(5, 1);
      w.i32(6, 3);  // LIST
      w.end();
      w.begin();
      w.i32(3, 2);
      w.string(4, "list");
      w.i32(5, 1);
      w.end();
    }
    w.begin();
    w.i32(1, static_cast<int>(c.type));
    w.i32(3, c.list || c.optional ? 1 : 0);
    w.string(4, c.list ? "element" : c.name);
    if (c.type == ParquetType::kByteArray) w.i32(6, 0);  // UTF8
    w.end();
  }
  w.i64(3, rows);
  w.list(4, 12, groups.size());
  for (size_t g = 0; g < groups.size(); ++g) {
    w.begin();
    w.list(1, 12, columns_.size());
    int64_t total = 0;
    for (size_t ci = 0; ci < columns_.size(); ++ci) {
      const Column& c = columns_[ci];
      const ChunkMeta& m = groups[g][ci];
      total += m.chunk.uncompressed;
      w.begin();
      w.i64(2, m.offset);
      w.begin_struct(3);
      w.i32(1, static_cast<int>(c.type));
      const bool dict = m.chunk.dict_offset >= 0;
      w.list(2, 5, dict ? 3 : 2);
      if (dict)
        w.zigzag(options_.page_version == 1 ? 2 : 8), w.zigzag(0), w.zigzag(3);
      else
        w.zigzag(0), w.zigzag(3);
      if (c.list) {
        w.list(3, 8, 3);
        w.binary(c.name), w.binary("list"), w.binary("element");
      } else {
        w.list(3, 8, 1);
        w.binary(c.name);
      }
      w.i32(4, static_cast<int>(options_.codec));
      w.i64(5, m.chunk.num_values);
      w.i64(6, m.chunk.uncompressed);
      w.i64(7, static_cast<int64_t>(m.chunk.bytes.size()));
      w.i64(9, m.offset + m.chunk.data_offset);
      if (dict) w.i64(11, m.offset + m.chunk.dict_offset);
      w.end();
      w.end();
    }
    w.i64(2, total);
    w.i64(3, group_rows[g]);
    w.end();
  }
  w.string(6, "dreamdojo.cpp parquet_writer");
  w.end();
  file += w.out;
  put_u32(file, static_cast<uint32_t>(w.out.size()));
  file += "PAR1";
  return file;
}

void ParquetWriter::write(const std::filesystem::path& path) const {
  if (path.has_parent_path()) std::filesystem::create_directories(path.parent_path());
  write_file_atomic(path, to_bytes());
}

}  // namespace dojo::io
