#include "core/mapped_file.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include "core/error.h"

namespace dojo {

MappedFile::~MappedFile() {
  if (base != nullptr) ::munmap(base, size);
}

std::shared_ptr<const MappedFile> MappedFile::map(int fd, size_t size, const std::filesystem::path& path) {
  auto file = std::make_shared<MappedFile>();
  file->path = path;
  if (size == 0) return file;
  void* base = ::mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_NORESERVE, fd, 0);
  if (base == MAP_FAILED) throw Error(path.string() + ": cannot memory-map: " + std::strerror(errno));
  file->base = base;
  file->size = size;
  return file;
}

std::shared_ptr<const MappedFile> MappedFile::open(const std::filesystem::path& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) throw Error(path.string() + ": " + std::strerror(errno));
  struct FdCloser {
    int fd;
    ~FdCloser() { ::close(fd); }
  } closer{fd};
  struct stat st {};
  if (::fstat(fd, &st) != 0) throw Error(path.string() + ": " + std::strerror(errno));
  if (!S_ISREG(st.st_mode)) throw Error(path.string() + ": not a regular file");
  return map(fd, static_cast<size_t>(st.st_size), path);
}

}  // namespace dojo
