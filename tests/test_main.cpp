// Test entry point: uses all cores, like the CLI does by default.
#include <gtest/gtest.h>

#include "core/blas_kernels.h"
#include "core/heap.h"
#include "core/runtime.h"

int main(int argc, char** argv) {
  dojo::use_the_cpus_blas_kernels(argv);  // as the CLI does: the tests time nothing, but run faster
  dojo::keep_freed_memory_in_the_heap();
  ::testing::InitGoogleTest(&argc, argv);
  dojo::set_threads(0);
  return RUN_ALL_TESTS();
}
