#include "infer/cuda_graph.h"

#include "core/error.h"

#ifdef DOJO_CUDA_GRAPHS
#include <ATen/autocast_mode.h>
#include <ATen/cuda/CUDAGraph.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#endif

#include <string>

namespace dojo::infer {

#ifdef DOJO_CUDA_GRAPHS

struct CapturedCall::Graph {
  at::cuda::CUDAGraph graph;
  c10::DeviceIndex device = 0;
};

bool CapturedCall::available() { return true; }

CapturedCall::CapturedCall(const std::function<void()>& body, int device_index,
                           const CapturedCall* share_memory_with)
    : graph_(std::make_unique<Graph>()) {
  // Streams belong to a device: without this guard a tensor on cuda:1 would launch on that
  // device's own stream while the capture listens on the current device's, and capture nothing.
  c10::cuda::OptionalCUDAGuard on_device;
  if (device_index >= 0) on_device.set_index(static_cast<c10::DeviceIndex>(device_index));
  graph_->device = c10::cuda::current_device();
  // Capture needs a stream of its own. It starts after the current stream's queued work (the
  // buffers the body reads were just written there), and that stream waits for it after.
  const auto current = c10::cuda::getCurrentCUDAStream();
  const auto side = c10::cuda::getStreamFromPool();
  current.synchronize();
  // Autocast's cast cache would keep tensors made during capture past it; the weights are
  // pre-cast anyway (StreamingEngine::Options::cast_weights).
  const bool cast_cache = at::autocast::is_autocast_cache_enabled();
  {
    c10::cuda::CUDAStreamGuard on_side(side);
    try {
      body();  // eager warm-up on the side stream: cuBLAS/attention workspaces exist before capture
      at::autocast::set_autocast_cache_enabled(false);
      const auto mode = cudaStreamCaptureModeThreadLocal;
      if (share_memory_with != nullptr)
        graph_->graph.capture_begin(share_memory_with->graph_->graph.pool(), mode);
      else
        graph_->graph.capture_begin({0, 0}, mode);
      try {
        body();
      } catch (...) {
        try {
          graph_->graph.capture_end();
        } catch (...) {
        }
        throw;
      }
      graph_->graph.capture_end();
    } catch (const std::exception& e) {
      at::autocast::set_autocast_cache_enabled(cast_cache);
      side.synchronize();
      throw Error(std::string("CUDA graph capture failed: ") + e.what());
    }
    at::autocast::set_autocast_cache_enabled(cast_cache);
  }
  side.synchronize();
}

CapturedCall::~CapturedCall() = default;

void CapturedCall::replay() {
  c10::cuda::CUDAGuard on_device(graph_->device);
  graph_->graph.replay();
}

#else

struct CapturedCall::Graph {};

bool CapturedCall::available() { return false; }

CapturedCall::CapturedCall(const std::function<void()>&, int, const CapturedCall*) {
  throw Error("CUDA graphs: this build has no CUDA libtorch (rebuild against one to capture graphs)");
}

CapturedCall::~CapturedCall() = default;

void CapturedCall::replay() {}

#endif

}  // namespace dojo::infer
