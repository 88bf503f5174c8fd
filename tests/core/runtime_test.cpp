#include "core/runtime.h"

#include <nlohmann/json.hpp>

#include "core/error.h"
#include "test_util.h"

namespace dojo {

TEST(Runtime, SetThreadsIsHonoured) {
  const int before = threads();
  set_threads(1);
  EXPECT_EQ(threads(), 1);
  set_threads(2);
  EXPECT_EQ(threads(), 2);
  set_threads(before);
}

TEST(Runtime, ParseDevice) {
  EXPECT_TRUE(parse_device("cpu").is_cpu());
  EXPECT_THROW(parse_device("tpu"), UsageError);
  if (!cuda_available()) {
    EXPECT_TRUE(parse_device("auto").is_cpu());
    EXPECT_THROW(parse_device("cuda"), UsageError);
  }
}

TEST(Runtime, DeviceParse_CUDA) {
  DOJO_REQUIRE_CUDA();
  EXPECT_TRUE(parse_device("cuda:0").is_cuda());
  EXPECT_TRUE(parse_device("auto").is_cuda());
}

TEST(Runtime, VersionInfoHasRequiredFields) {
  const auto info = version_info();
  for (const char* key : {"version", "git_commit", "torch_version", "cuda_available", "blas", "threads"})
    EXPECT_TRUE(info.contains(key)) << key;
  EXPECT_FALSE(info["blas"].get<std::string>().empty());
}

}  // namespace dojo
