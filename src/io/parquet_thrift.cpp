// Parquet footer and page-header decoding: FileMetaData's parts and PageHeader read with the
// Thrift compact protocol of parquet_thrift.h (other fields are skipped).
#include "io/parquet_thrift.h"

namespace dojo::io::parquet_detail {

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

}  // namespace dojo::io::parquet_detail
