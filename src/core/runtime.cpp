#include "core/runtime.h"

#include <ATen/Parallel.h>
#include <dlfcn.h>
#include <torch/torch.h>
#include <unistd.h>

#include <cstdlib>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>

#include "core/blas_kernels.h"
#include "core/error.h"
#include "dojo_git_commit.h"  // generated at build time: DOJO_GIT_COMMIT

namespace dojo {

void set_threads(int threads) {
  // OMP_NUM_THREADS, as PyTorch reads it: `dojo launch` gives each of its processes a share of the
  // cores that way.
  if (const char* omp = std::getenv("OMP_NUM_THREADS"); threads <= 0 && omp != nullptr)
    threads = std::max(0, std::atoi(omp));
  if (threads <= 0) {
    const unsigned hw = std::thread::hardware_concurrency();
    threads = hw > 0 ? static_cast<int>(hw) : 1;
  }
  torch::set_num_threads(threads);
  // ATen sizes a thread's OpenMP team from the process-wide count the first time that thread
  // runs a parallel op. Settle it for this thread now, so a worker thread that later limits
  // itself cannot leave the caller with one thread (the demo trained single-threaded that way:
  // its data-generation workers ran before the main thread's first parallel op).
  at::internal::lazy_init_num_threads();
  // The inter-op pool may be sized only once per process, before it is used.
  static bool inter_op_set = false;
  if (!inter_op_set) {
    inter_op_set = true;
    try {
      at::set_num_interop_threads(std::max(1, threads / 2));
    } catch (const std::exception&) {
      // Already started by an earlier parallel op: keep its size.
    }
  }
}

int threads() { return torch::get_num_threads(); }

void use_one_thread_in_this_thread() {
  at::internal::lazy_init_num_threads();  // first, or this thread's first parallel op undoes the rest
  // omp_set_num_threads sizes the calling thread's team only. It is looked up in the OpenMP
  // runtime libtorch already loaded (system libgomp, or the copy a pip wheel bundles) instead
  // of linking one, which could put two OpenMP runtimes in the process.
  using SetNumThreads = void (*)(int);
  static const auto omp_set = reinterpret_cast<SetNumThreads>(dlsym(RTLD_DEFAULT, "omp_set_num_threads"));
  if (omp_set != nullptr)
    omp_set(1);
  else
    at::set_num_threads(1);  // no OpenMP: the pool is process-wide anyway
}

ScopedThreads::ScopedThreads(int n) : saved_(threads()) { set_threads(std::max(1, std::min(n, saved_))); }
ScopedThreads::~ScopedThreads() { set_threads(saved_); }

int64_t resident_memory_bytes() {
  std::ifstream statm("/proc/self/statm");
  int64_t pages_total = 0, pages_resident = 0;
  if (!(statm >> pages_total >> pages_resident)) return 0;
  return pages_resident * static_cast<int64_t>(sysconf(_SC_PAGESIZE));
}

int matmul_bound_threads() {
  static const bool blas_has_own_pool = blas_library().find("pthread") != std::string::npos;
  return blas_has_own_pool ? 1 : threads();
}

bool cuda_available() { return torch::cuda::is_available(); }
int cuda_device_count() { return cuda_available() ? static_cast<int>(torch::cuda::device_count()) : 0; }

void synchronize(const c10::Device& device) {
  if (device.is_cuda()) torch::cuda::synchronize(device.has_index() ? device.index() : -1);
}

c10::Device parse_device(const std::string& name) {
  if (name == "auto") return cuda_available() ? torch::Device(torch::kCUDA, 0) : torch::Device(torch::kCPU);
  if (name == "cpu") return torch::Device(torch::kCPU);
  if (name.rfind("cuda", 0) == 0) {
    if (!cuda_available())
      throw UsageError("device '" + name + "' requested but CUDA is not available in this build/machine");
    int index = 0;
    if (name.size() > 4) {
      if (name[4] != ':') throw UsageError("unknown device '" + name + "' (use cpu, cuda, cuda:N or auto)");
      try {
        index = std::stoi(name.substr(5));
      } catch (const std::exception&) {
        throw UsageError("unknown device '" + name + "' (use cpu, cuda, cuda:N or auto)");
      }
      if (index < 0 || index >= cuda_device_count())
        throw UsageError("device '" + name + "' out of range: " + std::to_string(cuda_device_count()) +
                         " CUDA device(s)");
    }
    return torch::Device(torch::kCUDA, static_cast<c10::DeviceIndex>(index));
  }
  throw UsageError("unknown device '" + name + "' (use cpu, cuda, cuda:N or auto)");
}

std::string blas_library() {
  // Force the BLAS to be loaded (libtorch may bind it lazily).
  torch::NoGradGuard no_grad;
  (void)torch::mm(torch::ones({2, 2}), torch::ones({2, 2}));
  std::ifstream maps("/proc/self/maps");
  std::string line;
  std::string found;
  while (std::getline(maps, line)) {
    const auto slash = line.rfind('/');
    if (slash == std::string::npos) continue;
    const std::string path = line.substr(line.find('/'));
    const std::string file = line.substr(slash + 1);
    if (file.find("openblas") != std::string::npos) {
      if (path.find("pthread") != std::string::npos) return "openblas-pthread";
      if (path.find("openmp") != std::string::npos) return "openblas-openmp";
      found = "openblas";
    } else if (file.find("libmkl") != std::string::npos) {
      return "mkl";
    } else if (file.find("libblis") != std::string::npos) {
      found = "blis";
    } else if (file.find("libblas.so") != std::string::npos && found.empty()) {
      found = "reference-blas (" + path + ")";
    }
  }
  if (found.empty()) return at::hasMKL() ? "mkl (static)" : "unknown";
  return found;
}

std::string version_string() { return DOJO_VERSION; }
std::string git_commit() { return DOJO_GIT_COMMIT; }
std::string torch_version() {
#ifdef TORCH_VERSION
  return TORCH_VERSION;
#else
  return std::to_string(TORCH_VERSION_MAJOR) + "." + std::to_string(TORCH_VERSION_MINOR) + "." +
         std::to_string(TORCH_VERSION_PATCH);
#endif
}

bool plain_kernels() {
  static const bool plain = [] {
    const char* value = std::getenv("DOJO_PLAIN_KERNELS");
    return value != nullptr && std::string(value) == "1";
  }();
  return plain;
}

nlohmann::json version_info() {
  nlohmann::json info;
  info["version"] = version_string();
  info["git_commit"] = git_commit();
  info["torch_version"] = torch_version();
  info["cuda_available"] = cuda_available();
  info["cuda_devices"] = cuda_device_count();
  info["blas"] = blas_library();
  if (const auto kernels = blas_kernels(); !kernels.empty()) info["blas_kernels"] = kernels;
  info["threads"] = threads();
  info["plain_kernels"] = plain_kernels();
  info["hardware_threads"] = std::thread::hardware_concurrency();
#ifdef DOJO_WITH_SIM
  info["sim"] = true;
#else
  info["sim"] = false;
#endif
  return info;
}

}  // namespace dojo
