// Parquet page decoding: page decompression (snappy, zstd), RLE/bit-packed hybrid levels, PLAIN
// values and dictionary pages, for one leaf column across its row groups.
#include "io/parquet_decode.h"

#include <snappy-c.h>
#include <zstd.h>

#include <cstring>

#include "core/error.h"
#include "io/parquet_thrift.h"

namespace dojo::io {

using namespace parquet_detail;

namespace {

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

}  // namespace dojo::io
