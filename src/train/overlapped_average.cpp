#include "train/overlapped_average.h"

#include <torch/csrc/autograd/function.h>
#include <torch/csrc/autograd/utils/lambda_post_hook.h>
#include <torch/csrc/autograd/variable.h>

#include <algorithm>

#include "core/error.h"

namespace dojo::train {

OverlappedGradientAverage::OverlappedGradientAverage(const std::vector<torch::Tensor>& params,
                                                     const std::vector<int64_t>& offsets,
                                                     torch::Tensor flat_grad, int world, StartSum start_sum,
                                                     int64_t bucket_bytes)
    : flat_grad_(std::move(flat_grad)), world_(world), start_sum_(std::move(start_sum)) {
  DOJO_CHECK(params.size() == offsets.size() && !params.empty(),
             "overlapped all-reduce: one offset per parameter");
  DOJO_CHECK(flat_grad_.dim() == 1 && flat_grad_.is_contiguous() && world_ >= 1 && bucket_bytes > 0,
             "overlapped all-reduce: a contiguous flat gradient, a world and a bucket size");
  // Buckets from the end of the flat gradient; each parameter's elements lie in one bucket.
  std::vector<size_t> order(params.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return offsets[a] > offsets[b]; });
  bucket_of_.assign(params.size(), 0);
  const int64_t bucket_elements = std::max<int64_t>(1, bucket_bytes / flat_grad_.element_size());
  int64_t expected_end = flat_grad_.numel();  // parameters tile the flat gradient, without gaps
  for (const size_t i : order) {
    const int64_t begin = offsets[i], end = begin + params[i].numel();
    DOJO_CHECK(begin >= 0 && end == expected_end,
               "overlapped all-reduce: the parameters must tile the flat gradient");
    expected_end = begin;
    if (buckets_.empty() || buckets_.back().end - buckets_.back().begin >= bucket_elements)
      buckets_.push_back(Bucket{begin, end, 0, 0});
    auto& bucket = buckets_.back();
    bucket.begin = begin;
    bucket_of_[i] = buckets_.size() - 1;
    if (params[i].numel() > 0) ++bucket.parameters;
  }
  DOJO_CHECK(expected_end == 0, "overlapped all-reduce: the parameters must tile the flat gradient");
  // A hook after each parameter's gradient accumulator: the gradient in the flat buffer is final
  // for this pass once it has run.
  for (size_t i = 0; i < params.size(); ++i) {
    if (params[i].numel() == 0) continue;
    auto accumulator = torch::autograd::impl::grad_accumulator(params[i]);
    DOJO_CHECK(accumulator != nullptr, "overlapped all-reduce: parameter " + std::to_string(i) +
                                           " is not a leaf that requires a gradient");
    hook_keys_.push_back(accumulator->add_post_hook(std::make_unique<torch::autograd::utils::LambdaPostHook>(
        [this, i](const torch::autograd::variable_list& outputs, const torch::autograd::variable_list&) {
          on_gradient(i);
          return outputs;
        })));
    accumulators_.push_back(std::move(accumulator));
  }
}

OverlappedGradientAverage::~OverlappedGradientAverage() {
  for (size_t k = 0; k < accumulators_.size(); ++k) accumulators_[k]->del_post_hook(hook_keys_[k]);
}

void OverlappedGradientAverage::arm() {
  std::lock_guard<std::mutex> lock(mutex_);
  DOJO_CHECK(!armed_ && waits_.empty(), "overlapped all-reduce: armed twice without finish()");
  for (auto& b : buckets_) b.pending = b.parameters;
  next_ = 0;
  failure_ = nullptr;
  stats_ = Stats{static_cast<int64_t>(buckets_.size()), 0};
  armed_ = true;
}

void OverlappedGradientAverage::on_gradient(size_t param) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!armed_ || failure_) return;
  --buckets_[bucket_of_[param]].pending;
  // Exceptions must not cross autograd's engine: kept, and thrown by finish().
  try {
    const size_t before = next_;
    start_ready_buckets();
    stats_.started_in_backward += static_cast<int64_t>(next_ - before);
  } catch (...) {
    failure_ = std::current_exception();
  }
}

void OverlappedGradientAverage::start_ready_buckets() {
  while (next_ < buckets_.size() && buckets_[next_].pending <= 0) {
    const auto& b = buckets_[next_];
    waits_.push_back(start_sum_(flat_grad_.narrow(0, b.begin, b.end - b.begin)));
    ++next_;
  }
}

void OverlappedGradientAverage::finish() {
  std::vector<Wait> waits;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    DOJO_CHECK(armed_, "overlapped all-reduce: finish() without arm()");
    armed_ = false;
    if (!failure_) {
      try {
        for (auto& b : buckets_) b.pending = 0;  // what the pass did not reach is final as it is
        start_ready_buckets();
      } catch (...) {
        failure_ = std::current_exception();
      }
    }
    waits.swap(waits_);
  }
  // Every started sum is waited for, even after a failure, so none runs on into the next step.
  std::exception_ptr failure = failure_;
  for (auto& wait : waits) {
    try {
      wait();
    } catch (...) {
      if (!failure) failure = std::current_exception();
    }
  }
  if (failure) std::rethrow_exception(failure);
  torch::NoGradGuard no_grad;
  flat_grad_.mul_(1.0 / static_cast<double>(world_));
}

}  // namespace dojo::train
