// Process-wide runtime facts and settings: intra-op threads, device selection, build info.
#pragma once

#include <cstdint>
#include <string>

#include <nlohmann/json_fwd.hpp>

namespace c10 {
struct Device;
}

namespace dojo {

// Sets the intra-op (and inter-op, once) thread count. threads <= 0 means OMP_NUM_THREADS when set
// (dojo launch shares the cores among its processes that way), else all cores.
// Debian's libtorch defaults to one thread, so every entry point calls this.
void set_threads(int threads);
int threads();
// For worker threads (decoders, renderers) whose torch ops are small: one intra-op thread in the
// calling thread only. at::set_num_threads(1) there would also change the process-wide count that
// every thread's first parallel op adopts.
void use_one_thread_in_this_thread();

// Holds the intra-op thread count at `n` (at most the current count) for a scope, then restores
// it. For matmul-bound stages on CPU: see matmul_bound_threads().
class ScopedThreads {
 public:
  explicit ScopedThreads(int n);
  ~ScopedThreads();
  ScopedThreads(const ScopedThreads&) = delete;
  ScopedThreads& operator=(const ScopedThreads&) = delete;

 private:
  int saved_;
};

// Intra-op threads for CPU work whose time goes to matrix multiplies (transformer training and
// sampling). When the BLAS library runs its own thread pool (OpenBLAS' pthread build, Debian's
// default), it already uses every core inside each matmul, and a second OpenMP thread only spins
// against it between ops: measured on 2 cores, the DiT trained at 29.6 clips/s with one OpenMP
// thread and 10.7 with two, the LAM at 9.8 vs 6.3 steps/s. Then 1; otherwise threads().
int matmul_bound_threads();

// True when the environment sets DOJO_PLAIN_KERNELS to 1: every optimised kernel (the fused
// optimizer step, the fused inference kernels of the DiT) runs its plain libtorch reference
// path instead, for comparison and for ruling them out when something looks wrong. Read once.
bool plain_kernels();

// Resident set size of this process now, in bytes (/proc/self/statm; 0 where unavailable).
int64_t resident_memory_bytes();

bool cuda_available();
int cuda_device_count();
// Waits until the work queued on `device` has finished (no-op on the CPU), so that a wall clock
// read afterwards covers it: CUDA kernels run asynchronously to the host.
void synchronize(const c10::Device& device);

// Parses "cpu", "cuda", "cuda:N" or "auto" (CUDA when available, else CPU). Throws
// dojo::UsageError on an unknown name or a CUDA request without CUDA.
c10::Device parse_device(const std::string& name);

// The BLAS library actually mapped into this process (e.g. "openblas-pthread"), found by
// reading /proc/self/maps after a matrix multiply forced it to load.
std::string blas_library();

std::string version_string();
std::string git_commit();
std::string torch_version();

// {version, git_commit, torch_version, cuda_available, cuda_devices, blas, threads, ...}
nlohmann::json version_info();

}  // namespace dojo
