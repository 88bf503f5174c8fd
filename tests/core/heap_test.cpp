#include "core/heap.h"

#include <malloc.h>

#include <cstdlib>
#include <cstring>

#include "test_util.h"

namespace dojo {

// An 8 MiB block (glibc's default would map it on its own and unmap it on free) comes from the
// heap once the settings are made; the variables that override them are not set in the tests.
TEST(Heap, LargeBlocksComeFromTheHeap) {
  if (std::getenv("GLIBC_TUNABLES") != nullptr || std::getenv("MALLOC_MMAP_THRESHOLD_") != nullptr)
    GTEST_SKIP() << "the environment sets the allocator";
  ASSERT_TRUE(keep_freed_memory_in_the_heap());
  const auto mapped_before = mallinfo2().hblks;  // blocks with a mapping of their own
  void* block = std::malloc(8 << 20);
  ASSERT_NE(block, nullptr);
  std::memset(block, 1, 8 << 20);
  const auto mapped_with_block = mallinfo2().hblks;
  std::free(block);
  EXPECT_EQ(mapped_with_block, mapped_before);
}

}  // namespace dojo
