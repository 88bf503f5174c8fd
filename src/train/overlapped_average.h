// The gradient all-reduce of data parallelism overlapped with the backward pass, for trainers whose
// gradients live in one flat buffer (FusedAdamW: the world model and distillation).
//
// The flat gradient is cut into buckets of about `bucket_bytes`, from its end: the backward pass
// reaches the last parameters (the final layer, the last blocks) first. A hook on each parameter's
// gradient accumulator counts the parameters of its bucket that are done; when a bucket is complete
// its all-reduce starts at once, on Gloo's threads, while autograd goes on with earlier layers.
// Buckets start strictly in order (bucket k only after k - 1), so every rank issues the same
// collectives in the same sequence whatever order its gradients arrive in; finish() starts the
// ones the pass did not complete (a parameter without a gradient this step), waits for all and
// divides by the world. The arithmetic is the one of DataParallel::average_gradients (a sum over
// ranks, then x (1 / world)), on the same numbers: the parameters are bit for bit the same.
//
// Only the step's last backward pass is armed (arm()): earlier micro-batches only accumulate.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <exception>
#include <functional>
#include <memory>
#include <mutex>
#include <vector>

namespace torch::autograd {
struct Node;
}

namespace dojo::train {

class OverlappedGradientAverage {
 public:
  // Starts summing `flat` (contiguous) over the ranks in place; the function returned waits for the
  // sum (and throws dojo::Error when a peer is lost). Every rank starts the same sums in order.
  using Wait = std::function<void()>;
  using StartSum = std::function<Wait(const torch::Tensor& flat)>;

  // params[i]'s gradient is flat_grad[offsets[i], offsets[i] + numel) (FusedAdamW's layout).
  OverlappedGradientAverage(const std::vector<torch::Tensor>& params, const std::vector<int64_t>& offsets,
                            torch::Tensor flat_grad, int world, StartSum start_sum,
                            int64_t bucket_bytes = 8 << 20);
  ~OverlappedGradientAverage();  // removes its hooks
  OverlappedGradientAverage(const OverlappedGradientAverage&) = delete;
  OverlappedGradientAverage& operator=(const OverlappedGradientAverage&) = delete;

  // The next backward pass is the step's last: complete buckets start as it runs.
  void arm();
  // After that pass: starts the buckets not started yet, waits for every sum, divides by world.
  void finish();

  struct Stats {
    int64_t buckets = 0;              // all-reduces a step
    int64_t started_in_backward = 0;  // of them, started before the backward pass returned
  };
  Stats last_step() const { return stats_; }

 private:
  struct Bucket {
    int64_t begin = 0, end = 0;  // elements of the flat gradient
    int64_t parameters = 0, pending = 0;
  };
  void on_gradient(size_t param);  // a parameter's gradient is final for this pass
  void start_ready_buckets();      // under mutex_: buckets next_ .. in order while complete

  torch::Tensor flat_grad_;
  int world_;
  StartSum start_sum_;
  std::vector<Bucket> buckets_;  // bucket 0 holds the end of the flat gradient
  std::vector<size_t> bucket_of_;
  std::vector<std::shared_ptr<torch::autograd::Node>> accumulators_;  // kept alive: they carry the hooks
  std::vector<uintptr_t> hook_keys_;
  std::vector<Wait> waits_;
  std::mutex mutex_;
  bool armed_ = false;
  size_t next_ = 0;  // the next bucket to start
  std::exception_ptr failure_;
  Stats stats_;
};

}  // namespace dojo::train
