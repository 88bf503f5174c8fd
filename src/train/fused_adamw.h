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
// that use it (WmTrainer: world model, distillation; LamTrainer) train every parameter they hand it.
//
// ZeRO-1 (shard()): under data parallelism each rank keeps the moments of its own slice of the
// flat parameters only (1/world of them), updates that slice, gathers every rank's updated slice
// of the parameters, then updates the EMA of the other ranks' elements itself. The gradient is
// the same on every rank (averaged before step()), so the norm, the clipping and each element's
// update are the ones an unsharded run computes: parameters and EMA agree bit for bit.
// Checkpoints stay whole: gather_state() assembles every rank's moments on rank 0 before a save.
//
// Reference path: with DOJO_PLAIN_KERNELS=1 (core/runtime.h, plain_kernels()) step() runs
// clip_grad_norm_, AdamW::step and diffusion::ema_update instead, on the same tensors.
#pragma once

#include <torch/optim/adamw.h>
#include <torch/types.h>

#include <functional>
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
  // into the flat buffers and the state points at them again (sharded: this rank's slice is
  // copied and the state is emptied, so the whole moments do not stay in memory).
  void adopt_state();

  // What sharding needs from the process group (DataParallel's in-place gathers): every rank's
  // `mine` [n] copied into out[r], on every rank or on rank 0 only (out empty elsewhere).
  using Gather = std::function<void(const torch::Tensor& mine, const std::vector<torch::Tensor>& out)>;
  struct Collectives {
    int rank = 0, world = 1;
    Gather all_gather, gather_to_main;
  };
  // ZeRO-1 from now on: moments (a resumed state's included) are kept for this rank's slice only.
  // Refused under DOJO_PLAIN_KERNELS (its reference step is torch's AdamW over every parameter).
  void shard(Collectives collectives);
  // Sharded: gathers the whole moments into rank 0's optimizer state, in host memory (a
  // collective: every rank calls it, before rank 0 saves); freed by the next zero_grad(). The
  // other ranks hold no more than before. Unsharded: nothing to do, the state views the moments.
  void gather_state();
  // Moment elements this process holds (2 per parameter unsharded; about 2 / world sharded).
  int64_t moment_elements() const { return exp_avg_.numel() + exp_avg_sq_.numel(); }

  const torch::Tensor& flat_grad() const { return grad_; }
  // Where each parameter's elements start in the flat buffers, in the order given.
  const std::vector<int64_t>& offsets() const { return offsets_; }

 private:
  torch::optim::AdamW& optimizer_;
  std::vector<torch::Tensor> params_, ema_;
  std::vector<int64_t> offsets_;
  torch::Tensor param_, grad_, ema_flat_;  // [N] each
  // [own_]: elements begin_ .. begin_ + own_ (all N unsharded); empty before the first step.
  torch::Tensor exp_avg_, exp_avg_sq_;
  int64_t step_ = 0;
  // ZeRO-1: slices of shard_ elements, this rank's from begin_ (own_ of them: the last may be short).
  Collectives collectives_;
  int64_t shard_ = 0, begin_ = 0, own_ = 0;

  bool sharded() const { return collectives_.world > 1; }
  void make_moments();  // zeros for the elements held here, unless they exist
  // The optimizer's state -> views of whole moments m, v [N], at step_.
  void point_state(const torch::Tensor& m, const torch::Tensor& v);
  void plain_step(double max_norm, double lr, double ema_beta, double& norm);
  // Sharded: every rank's slice of `flat` [N] into place on every rank (into_main: into `whole`
  // [N] on rank 0 only), in chunks, so no temporary of N elements is made.
  void gather_slices(const torch::Tensor& mine, const torch::Tensor& whole, bool into_main);
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
// Its EMA line alone, ema <- beta ema + (1 - beta) param: the same bits for the same inputs.
void fused_ema_update(float* ema, const float* param, int64_t n, double ema_beta);

}  // namespace dojo::train
