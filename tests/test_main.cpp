// Test entry point: uses all cores, like the CLI does by default.
#include <gtest/gtest.h>

#include "core/runtime.h"

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  dojo::set_threads(0);
  return RUN_ALL_TESTS();
}
