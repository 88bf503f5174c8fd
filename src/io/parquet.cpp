// ParquetFile: reads the footer, builds the schema tree and serves the typed column reads. The
// Thrift metadata lives in parquet_thrift.{h,cpp}, page and value decoding in parquet_decode.{h,cpp}.
#include "io/parquet.h"

#include <cstring>
#include <fstream>

#include "core/error.h"
#include "io/parquet_decode.h"
#include "io/parquet_thrift.h"

namespace dojo::io {

using namespace parquet_detail;

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
