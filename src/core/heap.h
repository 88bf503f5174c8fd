// How the C library's allocator returns freed memory to the kernel.
//
// glibc hands blocks above its mmap threshold (128 KiB, raised adaptively up to 32 MiB) back to
// the kernel on free, and trims the top of the heap beyond 128 KiB; libtorch frees and allocates
// tensors of the same sizes every training step, so their pages faulted in again each time: the
// kernel's page-fault path took 14% of the main thread's time in a profile of the small DiT's
// training on 2 cores (perf); keeping freed memory in the heap cut page faults 10x and raised it
// from 2.41-2.55 to 2.73-3.05 steps/s (docs/benchmarks.md). The price is a resident size that
// stays at its peak.
#pragma once

namespace dojo {

// Called first in main(): blocks up to 32 MiB (glibc's largest threshold) come from the heap, and
// the heap keeps up to 1 GiB free at its top instead of trimming, with 256 MiB of padding per
// growth. Environment variables that set these (MALLOC_MMAP_THRESHOLD_, MALLOC_TRIM_THRESHOLD_,
// MALLOC_TOP_PAD_, GLIBC_TUNABLES) win. Returns false where the C library refused a setting.
bool keep_freed_memory_in_the_heap();

}  // namespace dojo
