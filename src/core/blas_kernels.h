// OpenBLAS's kernel choice, checked once at process start.
//
// OpenBLAS (Debian's build has every x86-64 kernel set) picks one set when it loads, from the CPU's
// model number. A CPU newer than the library gets its oldest x86-64 set: Debian 12's OpenBLAS
// 0.3.21 on an AVX-512 Xeon of this project's 2-core machines reported "Prescott" (SSE3) and
// multiplied 1024^3 float32 matrices at 43 GFLOP/s, against 182 with its AVX-512 set (SkylakeX),
// which that CPU runs. The environment variable OPENBLAS_CORETYPE overrides the choice, but only at
// load time, so a process that finds a fallback set sets it and starts itself again.
#pragma once

#include <string>

namespace dojo {

// The kernel set OpenBLAS runs ("SkylakeX", "Haswell", "Prescott", ...); empty when the BLAS is
// not OpenBLAS (MKL inside PyTorch's own libtorch, say).
std::string blas_kernels();

// The kernel set this CPU should get: "SkylakeX" with AVX-512 (F, VL, BW, DQ), "Haswell" with
// AVX2 and FMA; empty otherwise.
std::string blas_kernels_for_this_cpu();

// True for the kernel sets OpenBLAS falls back to on a CPU it does not know, which predate AVX2.
bool is_fallback_blas_kernels(const std::string& name);

// Called first in main(), before any thread starts: when OpenBLAS runs a fallback set on a CPU
// with AVX2 or AVX-512 and OPENBLAS_CORETYPE is unset, sets it (blas_kernels_for_this_cpu()) and
// re-executes this program (/proc/self/exe) with the same arguments. Returns otherwise, also when
// the re-execution fails. A user's own OPENBLAS_CORETYPE is always kept.
void use_the_cpus_blas_kernels(char** argv);

}  // namespace dojo
