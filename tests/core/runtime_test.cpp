#include "core/runtime.h"

#include <nlohmann/json.hpp>
#include <thread>

#include "core/blas_kernels.h"
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

TEST(Runtime, WorkerThreadLimitStaysInTheWorker) {
  // The demo once trained on one core: its data workers limited themselves with
  // at::set_num_threads(1) before the main thread's first parallel op, which then adopted 1.
  // Replayed on a fresh thread standing in for main.
  const int before = threads();
  int main_threads = 0, worker_threads = 0, later_thread = 0;
  std::thread main_like([&] {
    set_threads(3);
    std::thread worker([&] {
      use_one_thread_in_this_thread();
      worker_threads = threads();
    });
    worker.join();
    main_threads = threads();
    std::thread later([&] { later_thread = threads(); });  // adopts the process-wide count
    later.join();
  });
  main_like.join();
  EXPECT_EQ(worker_threads, 1);
  EXPECT_EQ(main_threads, 3);
  EXPECT_EQ(later_thread, 3);
  set_threads(before);
}

TEST(Runtime, ScopedThreadsLowersAndRestores) {
  const int before = threads();
  set_threads(3);
  {
    ScopedThreads one(1);
    EXPECT_EQ(threads(), 1);
    {
      ScopedThreads more(8);  // never raises the count
      EXPECT_EQ(threads(), 1);
    }
    EXPECT_EQ(threads(), 1);
  }
  EXPECT_EQ(threads(), 3);
  // One thread exactly when the BLAS library brings its own pool.
  const bool own_pool = blas_library().find("pthread") != std::string::npos;
  EXPECT_EQ(matmul_bound_threads(), own_pool ? 1 : 3);
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

// The kernel sets OpenBLAS falls back to predate AVX2, in any spelling; its AVX2 and AVX-512 sets
// are not fallbacks.
TEST(Runtime, FallbackBlasKernelsAreTheOldOnes) {
  for (const char* old : {"Prescott", "PRESCOTT", "Core2", "Nehalem", "Sandybridge"})
    EXPECT_TRUE(is_fallback_blas_kernels(old)) << old;
  for (const char* current : {"Haswell", "SkylakeX", "Cooperlake", "Zen", ""})
    EXPECT_FALSE(is_fallback_blas_kernels(current)) << current;
  const auto wanted = blas_kernels_for_this_cpu();
  EXPECT_TRUE(wanted.empty() || wanted == "Haswell" || wanted == "SkylakeX") << wanted;
}

}  // namespace dojo
