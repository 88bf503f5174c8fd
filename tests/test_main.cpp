// Test entry point: uses all cores, like the CLI does by default.
#include <gtest/gtest.h>

#include <cstdlib>

#include "core/blas_kernels.h"
#include "core/heap.h"
#include "core/runtime.h"

int main(int argc, char** argv) {
  dojo::use_the_cpus_blas_kernels(argv);  // as the CLI does: the tests time nothing, but run faster
  dojo::keep_freed_memory_in_the_heap();
  ::testing::InitGoogleTest(&argc, argv);
  // A user's embodiment table (docs/new_robot.md) would change what the tests' datasets mean, in
  // this process and in every `dojo` it starts: the tests bring their own tables.
  unsetenv("DOJO_EMBODIMENTS");
  dojo::set_threads(0);
  return RUN_ALL_TESTS();
}
