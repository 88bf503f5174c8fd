#include "core/atomic_file.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstring>
#include <streambuf>
#include <string>
#include <vector>

#include "core/error.h"

namespace dojo {
namespace {

CrashHook& crash_hook() {
  static CrashHook hook;
  return hook;
}

std::string errno_text(int error) { return std::strerror(error); }

// An output stream buffer over a POSIX file descriptor. Remembers the first write error so the
// caller can report errno text ("No space left on device") instead of a bare stream failure.
class FdStreamBuf : public std::streambuf {
 public:
  explicit FdStreamBuf(int fd) : fd_(fd), buffer_(kBufferSize) {
    setp(buffer_.data(), buffer_.data() + buffer_.size());
  }
  int error() const { return error_; }

 protected:
  int_type overflow(int_type ch) override {
    if (!flush_buffer()) return traits_type::eof();
    if (!traits_type::eq_int_type(ch, traits_type::eof())) {
      *pptr() = traits_type::to_char_type(ch);
      pbump(1);
    }
    return traits_type::not_eof(ch);
  }

  std::streamsize xsputn(const char* data, std::streamsize count) override {
    // Small pieces go through the buffer; large ones straight to the file.
    if (count < static_cast<std::streamsize>(buffer_.size()) / 2) {
      std::streamsize done = 0;
      while (done < count) {
        if (pptr() == epptr() && !flush_buffer()) return done;
        const std::streamsize room = epptr() - pptr();
        const std::streamsize n = std::min(room, count - done);
        std::memcpy(pptr(), data + done, static_cast<size_t>(n));
        pbump(static_cast<int>(n));
        done += n;
      }
      return done;
    }
    if (!flush_buffer()) return 0;
    return write_all(data, count) ? count : 0;
  }

  int sync() override { return flush_buffer() ? 0 : -1; }

 private:
  static constexpr size_t kBufferSize = 1 << 20;

  bool flush_buffer() {
    const std::streamsize n = pptr() - pbase();
    if (n > 0 && !write_all(pbase(), n)) return false;
    setp(buffer_.data(), buffer_.data() + buffer_.size());
    return true;
  }

  // Writes in pieces of at most kBufferSize, with a crash point after each.
  bool write_all(const char* data, std::streamsize count) {
    if (error_ != 0) return false;
    while (count > 0) {
      const size_t piece = std::min(static_cast<size_t>(count), kBufferSize);
      const ssize_t n = ::write(fd_, data, piece);
      if (n < 0) {
        if (errno == EINTR) continue;
        error_ = errno;
        return false;
      }
      data += n;
      count -= n;
      crash_point("atomic:write");
    }
    return true;
  }

  int fd_;
  std::vector<char> buffer_;
  int error_ = 0;
};

std::filesystem::path temp_path_for(const std::filesystem::path& path) {
  static std::atomic<unsigned> counter{0};
  const std::string name =
      "." + path.filename().string() + ".tmp-" + std::to_string(::getpid()) + "-" + std::to_string(counter++);
  return path.parent_path() / name;
}

}  // namespace

void set_crash_hook(CrashHook hook) { crash_hook() = std::move(hook); }

void crash_point(const char* label) {
  if (crash_hook()) crash_hook()(label);
}

void fsync_directory(const std::filesystem::path& dir) {
  const std::string name = dir.empty() ? std::string(".") : dir.string();
  const int fd = ::open(name.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) throw Error("cannot open directory " + name + " to sync it: " + errno_text(errno));
  const int rc = ::fsync(fd);
  const int error = errno;
  ::close(fd);
  // Some file systems (and some FUSE mounts) refuse fsync on directories; nothing more to do there.
  if (rc != 0 && error != EINVAL && error != ENOTSUP)
    throw Error("cannot sync directory " + name + ": " + errno_text(error));
}

void write_file_atomic(const std::filesystem::path& path, const std::function<void(std::ostream&)>& writer) {
  DOJO_CHECK(!path.filename().empty(), "cannot write '" + path.string() + "': not a file name");
  const std::filesystem::path temp = temp_path_for(path);
  const int fd = ::open(temp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
  if (fd < 0) throw Error("cannot write " + path.string() + ": " + errno_text(errno));

  bool closed = false;
  auto fail = [&](const std::string& message) {
    if (!closed) ::close(fd);
    ::unlink(temp.c_str());
    throw Error("cannot write " + path.string() + ": " + message);
  };
  {
    FdStreamBuf buffer(fd);
    std::ostream out(&buffer);
    try {
      writer(out);
      out.flush();
    } catch (...) {
      ::close(fd);
      ::unlink(temp.c_str());
      throw;
    }
    if (buffer.error() != 0) fail(errno_text(buffer.error()));
    if (!out) fail("stream error");
  }
  if (::fsync(fd) != 0) fail(errno_text(errno));
  closed = true;
  if (::close(fd) != 0) fail(errno_text(errno));
  crash_point("atomic:before-rename");
  if (::rename(temp.c_str(), path.c_str()) != 0) fail(errno_text(errno));
  crash_point("atomic:renamed");
  fsync_directory(path.parent_path());
}

void write_file_atomic(const std::filesystem::path& path, std::string_view bytes) {
  write_file_atomic(path, [bytes](std::ostream& out) {
    out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  });
}

}  // namespace dojo
