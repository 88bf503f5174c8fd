#include "core/zip_archive.h"

#include <algorithm>
#include <cstring>

#include "core/error.h"

namespace dojo {
namespace {

constexpr uint32_t kLocalHeader = 0x04034b50;
constexpr uint32_t kCentralHeader = 0x02014b50;
constexpr uint32_t kEndOfDirectory = 0x06054b50;
constexpr uint32_t kZip64Locator = 0x07064b50;
constexpr uint32_t kZip64EndOfDirectory = 0x06064b50;
constexpr uint16_t kZip64ExtraId = 0x0001;

// Little-endian reads inside [data, data + size); every read is bounds-checked.
class Reader {
 public:
  Reader(const uint8_t* data, uint64_t size, const std::string& source)
      : data_(data), size_(size), source_(source) {}

  Error error(const std::string& message) const {
    return Error(source_ + ": not a valid ZIP archive: " + message);
  }
  void need(uint64_t offset, uint64_t length, const char* what) const {
    if (offset > size_ || length > size_ - offset)
      throw error(std::string(what) + " at byte " + std::to_string(offset) + " runs past the end (" +
                  std::to_string(size_) + " bytes)");
  }
  uint64_t uint(uint64_t offset, int bytes, const char* what) const {
    need(offset, static_cast<uint64_t>(bytes), what);
    uint64_t value = 0;
    for (int i = bytes - 1; i >= 0; --i) value = (value << 8) | data_[offset + static_cast<uint64_t>(i)];
    return value;
  }
  std::string text(uint64_t offset, uint64_t length, const char* what) const {
    need(offset, length, what);
    return std::string(reinterpret_cast<const char*>(data_ + offset), length);
  }

 private:
  const uint8_t* data_;
  uint64_t size_;
  const std::string& source_;
};

struct Directory {
  uint64_t offset = 0;
  uint64_t size = 0;
  uint64_t count = 0;
};

Directory find_directory(const Reader& in, uint64_t size) {
  // The end-of-directory record is the last 22 bytes plus a comment of at most 65535 bytes.
  if (size < 22) throw in.error("shorter than an end-of-directory record");
  const uint64_t lowest = size > 22 + 65535 ? size - 22 - 65535 : 0;
  for (uint64_t pos = size - 22 + 1; pos-- > lowest;) {
    if (in.uint(pos, 4, "end of directory") != kEndOfDirectory) continue;
    if (pos + 22 + in.uint(pos + 20, 2, "comment length") > size) continue;
    Directory dir;
    dir.count = in.uint(pos + 10, 2, "record count");
    dir.size = in.uint(pos + 12, 4, "directory size");
    dir.offset = in.uint(pos + 16, 4, "directory offset");
    // ZIP64: a locator just before points at the 64-bit end-of-directory record.
    if (pos >= 20 && in.uint(pos - 20, 4, "ZIP64 locator") == kZip64Locator) {
      const uint64_t record = in.uint(pos - 20 + 8, 8, "ZIP64 record offset");
      if (in.uint(record, 4, "ZIP64 end of directory") != kZip64EndOfDirectory)
        throw in.error("the ZIP64 locator points at byte " + std::to_string(record) +
                       ", which is no ZIP64 end-of-directory record");
      dir.count = in.uint(record + 32, 8, "ZIP64 record count");
      dir.size = in.uint(record + 40, 8, "ZIP64 directory size");
      dir.offset = in.uint(record + 48, 8, "ZIP64 directory offset");
    }
    in.need(dir.offset, dir.size, "central directory");
    return dir;
  }
  throw in.error("no end-of-directory record");
}

}  // namespace

bool ZipArchive::looks_like_zip(const uint8_t* data, uint64_t size) {
  return size >= 4 && data[0] == 'P' && data[1] == 'K' && data[2] == 3 && data[3] == 4;
}

ZipArchive ZipArchive::parse(const uint8_t* data, uint64_t size, const std::string& source) {
  ZipArchive archive;
  archive.data_ = data;
  archive.size_ = size;
  archive.source_ = source;
  const Reader in(data, size, archive.source_);
  const Directory dir = find_directory(in, size);
  // Each central header is at least 46 bytes: a count larger than the directory can hold is corrupt.
  if (dir.count > dir.size / 46) throw in.error("record count " + std::to_string(dir.count) + " too large");
  uint64_t pos = dir.offset;
  for (uint64_t i = 0; i < dir.count; ++i) {
    if (in.uint(pos, 4, "central header") != kCentralHeader)
      throw in.error("central header " + std::to_string(i) + " at byte " + std::to_string(pos) +
                     " has a bad signature");
    ZipRecord record;
    record.method = static_cast<uint16_t>(in.uint(pos + 10, 2, "method"));
    uint64_t compressed = in.uint(pos + 20, 4, "compressed size");
    uint64_t uncompressed = in.uint(pos + 24, 4, "size");
    const uint64_t name_length = in.uint(pos + 28, 2, "name length");
    const uint64_t extra_length = in.uint(pos + 30, 2, "extra length");
    const uint64_t comment_length = in.uint(pos + 32, 2, "comment length");
    uint64_t local = in.uint(pos + 42, 4, "local header offset");
    record.name = in.text(pos + 46, name_length, "record name");
    // ZIP64 extra field: the 64-bit values of the fields that read 0xFFFFFFFF, in this order.
    uint64_t extra = pos + 46 + name_length;
    const uint64_t extra_end = extra + extra_length;
    in.need(extra, extra_length, "extra field");
    while (extra + 4 <= extra_end) {
      const uint64_t id = in.uint(extra, 2, "extra id");
      const uint64_t length = in.uint(extra + 2, 2, "extra length");
      if (extra + 4 + length > extra_end)
        throw in.error("extra field of '" + record.name + "' runs past its header");
      if (id == kZip64ExtraId) {
        uint64_t field = extra + 4;
        auto next = [&](uint64_t& value) {
          if (value != 0xFFFFFFFFu) return;
          if (field + 8 > extra + 4 + length) throw in.error("short ZIP64 field in '" + record.name + "'");
          value = in.uint(field, 8, "ZIP64 field");
          field += 8;
        };
        next(uncompressed);
        next(compressed);
        next(local);
      }
      extra += 4 + length;
    }
    if (in.uint(local, 4, "local header") != kLocalHeader)
      throw in.error("record '" + record.name + "' points at byte " + std::to_string(local) +
                     ", which is no local header");
    const uint64_t local_name = in.uint(local + 26, 2, "local name length");
    const uint64_t local_extra = in.uint(local + 28, 2, "local extra length");
    record.data_offset = local + 30 + local_name + local_extra;
    record.size = record.method == 0 ? uncompressed : compressed;
    if (record.method == 0 && compressed != uncompressed)
      throw in.error("stored record '" + record.name + "' has compressed size " + std::to_string(compressed) +
                     " != size " + std::to_string(uncompressed));
    in.need(record.data_offset, record.size, ("data of '" + record.name + "'").c_str());
    archive.records_.push_back(std::move(record));
    pos += 46 + name_length + extra_length + comment_length;
  }
  return archive;
}

const ZipRecord* ZipArchive::find(const std::string& name) const {
  for (const auto& record : records_)
    if (record.name == name) return &record;
  return nullptr;
}

std::string_view ZipArchive::data(const ZipRecord& record) const {
  if (record.method != 0)
    throw Error(source_ + ": record '" + record.name + "' is compressed (method " +
                std::to_string(record.method) + "); torch.save archives store every record uncompressed");
  return std::string_view(reinterpret_cast<const char*>(data_ + record.data_offset), record.size);
}

}  // namespace dojo
