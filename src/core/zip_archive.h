// A read-only view of a ZIP archive held in memory: the container of torch.save files (.pt, .pth,
// .ckpt) and of every chunk inside a distributed checkpoint's .distcp files.
//
// Our own reader (about 150 lines) rather than libzip: torch stores every record uncompressed
// and 64-byte aligned so that tensors can be used in place, and a reader must hand out the
// record's position inside a memory map (and inside a byte range of a larger file, for DCP
// chunks), which libzip does not expose. Only stored records (method 0) can be read; ZIP64
// archives (files over 4 GiB, as the 14B checkpoints are) are understood. Every offset and length
// is checked against the bytes given; errors are dojo::Error naming `source` and the record.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

namespace dojo {

struct ZipRecord {
  std::string name;
  uint64_t data_offset = 0;  // first byte of the record's data, relative to the archive's start
  uint64_t size = 0;         // bytes of data
  uint16_t method = 0;       // 0 = stored; anything else is refused by data()
};

class ZipArchive {
 public:
  // Parses the central directory of the archive in [data, data + size). The bytes must outlive
  // the archive object. Throws dojo::Error naming `source` when they are not a ZIP archive.
  static ZipArchive parse(const uint8_t* data, uint64_t size, const std::string& source);
  // Whether the bytes start with a ZIP local-file signature ("PK\3\4").
  static bool looks_like_zip(const uint8_t* data, uint64_t size);

  const std::string& source() const { return source_; }
  const std::vector<ZipRecord>& records() const { return records_; }
  // The record called `name`, or nullptr.
  const ZipRecord* find(const std::string& name) const;
  // The data of a stored record, in place. Throws for a compressed record.
  std::string_view data(const ZipRecord& record) const;
  const uint8_t* bytes() const { return data_; }

 private:
  const uint8_t* data_ = nullptr;
  uint64_t size_ = 0;
  std::string source_;
  std::vector<ZipRecord> records_;
};

}  // namespace dojo
