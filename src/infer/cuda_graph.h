// A CUDA graph of one call: every kernel a function launches, captured once and replayed with a
// single launch. The 2B student's forward is ~4200 small ops whose host-side dispatch, not the
// GPU's arithmetic, set its pace (docs/benchmarks.md, "The 2B student on a GPU"); replaying them
// as one graph takes the host out of the loop.
//
// What a graph replays is fixed at capture: the same kernels on the same memory. Inputs go in by
// copying into tensors the captured function read (static buffers); outputs are the tensors it
// wrote, overwritten by every replay. Shapes, and anything the function decided on the host (a
// slot index, a loop count), must be what they were at capture.
//
// Capture is compiled only against a CUDA libtorch (DOJO_CUDA_GRAPHS, set by CMake); elsewhere
// available() is false and capturing throws.
#pragma once

#include <functional>
#include <memory>

namespace dojo::infer {

class CapturedCall {
 public:
  // True when this build can capture CUDA graphs.
  static bool available();
  // Runs `body` once eagerly on a side stream of CUDA device `device_index` (-1: the current one),
  // for lazy initialisation and library workspaces, then captures it there. Only this thread's
  // CUDA calls are held to the capture's rules (other threads may allocate meanwhile). With
  // share_memory_with, the graph's temporaries come from that graph's memory pool: safe for
  // graphs that never replay at the same time and whose outputs stay referenced. Throws
  // dojo::Error when capture fails (e.g. an op that synchronises with the host, a CPU tensor
  // copied in, out of memory), leaving no graph.
  explicit CapturedCall(const std::function<void()>& body, int device_index = -1,
                        const CapturedCall* share_memory_with = nullptr);
  ~CapturedCall();
  CapturedCall(const CapturedCall&) = delete;
  CapturedCall& operator=(const CapturedCall&) = delete;
  // Launches the captured kernels on the capture device's current stream.
  void replay();

 private:
  struct Graph;
  std::unique_ptr<Graph> graph_;
};

}  // namespace dojo::infer
