// One pass over flat buffers for the end of a training step: gradient clipping by global norm,
// AdamW and the EMA of the weights. torch::optim::AdamW, clip_grad_norm_ and an EMA loop walk the
// parameters one by one, about twenty element-wise operations per tensor and step (137 tensors in
// the small DiT: 2,700 operator calls, each reading and writing whole tensors); a Python profile of
// the same step put them at a fifth of its time. Here every parameter, gradient, moment and EMA
// weight is a view into one flat buffer of its kind, so the norm is one reduction and the update
// one loop that reads each number once.
//
// The optimizer object stays torch::optim::AdamW: its per-parameter state holds views of the flat
// moments, so checkpoints (train_util.h: adamw_state / load_adamw_state) are unchanged; after a
// resume replaced that state, adopt_state() copies it back into the flat buffers.
//
// One difference from torch::optim::AdamW: every parameter has a (zero-filled) gradient, so a
// parameter that got no gradient in a step is still decayed and counted as stepped; the trainers
// that use it (WmTrainer: world model, distillation) train every parameter they hand it.
//
// Reference path: with DOJO_PLAIN_KERNELS=1 (core/runtime.h, plain_kernels()) step() runs
// clip_grad_norm_, AdamW::step and diffusion::ema_update instead, on the same tensors.
#pragma once

#include <torch/optim/adamw.h>
#include <torch/types.h>

#include <vector>

namespace dojo::train {

class FusedAdamW {
 public:
  // `params` (all on one device, float32, requiring gradients) become views into one flat buffer,
  // as do their gradients; `ema` (empty: none) is the EMA copy of each, flattened the same way.
  // The tensors keep their identity, so modules and `optimizer` (built over `params`) still see
  // them. Moments come to exist at the first step, as in torch::optim::AdamW.
  FusedAdamW(torch::optim::AdamW& optimizer, std::vector<torch::Tensor> params,
             std::vector<torch::Tensor> ema = {});

  // Zeroes the flat gradient in place (the views must stay defined: autograd then accumulates
  // into them instead of replacing them).
  void zero_grad();
  // Clips the gradient to `max_norm` (<= 0 or infinite: no clipping), steps AdamW at learning rate
  // `lr` (the optimizer's other options as set), then ema <- beta * ema + (1 - beta) * param.
  // Returns the gradient's global norm before clipping.
  double step(double max_norm, double lr, double ema_beta);
  // After load_adamw_state replaced the optimizer's state: its moments and step count are copied
  // into the flat buffers and the state points at them again.
  void adopt_state();

  const torch::Tensor& flat_grad() const { return grad_; }

 private:
  torch::optim::AdamW& optimizer_;
  std::vector<torch::Tensor> params_, ema_;
  std::vector<int64_t> offsets_;
  torch::Tensor param_, grad_, exp_avg_, exp_avg_sq_, ema_flat_;  // [N] each
  int64_t step_ = 0;

  void point_state();  // the optimizer's state -> views of the flat moments, at step_
  void plain_step(double max_norm, double lr, double ema_beta, double& norm);
};

// The fused update on raw float arrays, exposed for its test against the tensor-op reference:
// p <- p (1 - lr wd); m <- b1 m + (1 - b1) g s; v <- b2 v + (1 - b2) (g s)^2;
// p <- p - lr / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t) + eps); e <- beta e + (1 - beta) p.
struct AdamwScalars {
  double lr, beta1, beta2, eps, weight_decay, grad_scale, ema_beta;
  int64_t step;  // 1 at the first update
};
// Sum of squares of n floats, accumulated in double.
double fused_squared_sum(const float* x, int64_t n);
void fused_adamw_update(float* param, const float* grad, float* exp_avg, float* exp_avg_sq, float* ema,
                        int64_t n, const AdamwScalars& s);

}  // namespace dojo::train
