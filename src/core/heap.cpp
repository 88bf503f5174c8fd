#include "core/heap.h"

#include <malloc.h>

#include <cstdlib>

namespace dojo {

bool keep_freed_memory_in_the_heap() {
#ifdef M_MMAP_THRESHOLD
  if (std::getenv("GLIBC_TUNABLES") != nullptr) return true;  // the user's own allocator settings
  bool ok = true;
  if (std::getenv("MALLOC_MMAP_THRESHOLD_") == nullptr) ok = mallopt(M_MMAP_THRESHOLD, 32 << 20) == 1 && ok;
  if (std::getenv("MALLOC_TRIM_THRESHOLD_") == nullptr) ok = mallopt(M_TRIM_THRESHOLD, 1 << 30) == 1 && ok;
  if (std::getenv("MALLOC_TOP_PAD_") == nullptr) ok = mallopt(M_TOP_PAD, 256 << 20) == 1 && ok;
  return ok;
#else
  return true;  // not glibc: its allocator, its defaults
#endif
}

}  // namespace dojo
