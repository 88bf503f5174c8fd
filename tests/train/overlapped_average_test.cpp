// The gradient all-reduce overlapped with the backward pass, in one process: a fake sum stands for
// the other ranks (each holding the same gradient), records which buckets start and when, and
// the averaged gradient must be the plain backward pass's, bucket by bucket in a fixed order.
#include "train/overlapped_average.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <stdexcept>

#include "core/error.h"
#include "core/state_dict.h"
#include "train/fused_adamw.h"

namespace dojo::train {
namespace {

struct Net {
  torch::nn::Sequential layers{torch::nn::Linear(16, 64), torch::nn::GELU(), torch::nn::Linear(64, 64),
                               torch::nn::GELU(), torch::nn::Linear(64, 8)};
  torch::nn::Linear unused{torch::nn::Linear(4, 4)};  // gets no gradient in any pass
  explicit Net(bool with_unused_) : with_unused(with_unused_) {}
  bool with_unused;
  std::vector<torch::Tensor> params() const {
    auto p = layers->parameters();
    if (with_unused)
      for (const auto& u : unused->parameters()) p.push_back(u);
    return p;
  }
};

struct Started {
  int64_t begin = 0, size = 0;
};

struct Fixture {
  explicit Fixture(bool with_unused = true) : net(with_unused) {}
  Net net;
  torch::optim::AdamW optimizer{net.params(), torch::optim::AdamWOptions(1e-3)};
  FusedAdamW fused{optimizer, net.params()};
  std::vector<Started> started;
  // `world` ranks with this rank's gradient each: the sum is world x the gradient.
  OverlappedGradientAverage::StartSum fake_sum(int world) {
    return [this, world](const torch::Tensor& flat) {
      const auto* base = fused.flat_grad().data_ptr<float>();
      started.push_back({flat.data_ptr<float>() - base, flat.numel()});
      torch::NoGradGuard no_grad;
      flat.mul_(static_cast<double>(world));
      return OverlappedGradientAverage::Wait([] {});
    };
  }
  torch::Tensor loss(int64_t seed) {
    torch::manual_seed(seed);
    return net.layers->forward(torch::randn({32, 16})).pow(2).mean();
  }
};

std::vector<torch::Tensor> grads_of(const std::vector<torch::Tensor>& params) {
  std::vector<torch::Tensor> g;
  for (const auto& p : params) g.push_back(p.grad().clone());
  return g;
}

TEST(OverlappedAverage, BucketsStartInOrderDuringTheBackwardPassAndAverageToThePlainGradient) {
  Fixture f;
  // Plain gradients of two accumulated micro-batches.
  f.fused.zero_grad();
  f.loss(1).div(2).backward();
  f.loss(2).div(2).backward();
  const auto plain = grads_of(f.net.params());

  // Buckets of 1 KiB from the end: the unused layer and the last Linear, the middle Linear (its
  // 64x64 weight alone is 16 KiB), the first Linear.
  OverlappedGradientAverage overlap(f.net.params(), f.fused.offsets(), f.fused.flat_grad(), 2, f.fake_sum(2),
                                    1 << 10);
  f.fused.zero_grad();
  f.loss(1).div(2).backward();  // not armed: accumulates only
  EXPECT_TRUE(f.started.empty());
  overlap.arm();
  f.loss(2).div(2).backward();
  const auto in_backward = f.started.size();
  overlap.finish();

  const auto stats = overlap.last_step();
  EXPECT_EQ(stats.started_in_backward, static_cast<int64_t>(in_backward));
  EXPECT_EQ(stats.buckets, static_cast<int64_t>(f.started.size()));
  EXPECT_EQ(stats.buckets, 3);
  // The unused layer sits at the end of the flat gradient, in bucket 0, which never completes
  // during the pass; the buckets behind it wait for it (the order is every rank's), so nothing
  // starts until finish().
  EXPECT_EQ(in_backward, 0u);
  // In order from the end of the flat gradient, covering it once.
  int64_t end = f.fused.flat_grad().numel();
  for (const auto& s : f.started) {
    EXPECT_EQ(s.begin + s.size, end);
    end = s.begin;
  }
  EXPECT_EQ(end, 0);
  const auto averaged = grads_of(f.net.params());
  for (size_t i = 0; i < plain.size(); ++i)
    EXPECT_TRUE(torch::equal(averaged[i], plain[i])) << "parameter " << i;
}

TEST(OverlappedAverage, StartsBucketsWhileTheBackwardPassRuns) {
  Fixture f(/*with_unused=*/false);  // every parameter gets a gradient in the pass
  const auto params = f.net.params();
  auto& fused = f.fused;
  std::vector<int64_t> started_at;
  // 4 ranks: x 4 then x 1/4 gives the gradient's bits back.
  OverlappedGradientAverage overlap(
      params, fused.offsets(), fused.flat_grad(), 4,
      [&](const torch::Tensor& flat) {
        started_at.push_back(flat.data_ptr<float>() - fused.flat_grad().data_ptr<float>());
        torch::NoGradGuard no_grad;
        flat.mul_(4.0);
        return OverlappedGradientAverage::Wait([] {});
      },
      1 << 10);
  fused.zero_grad();
  f.loss(3).backward();
  const auto plain = grads_of(params);
  fused.zero_grad();
  overlap.arm();
  f.loss(3).backward();
  EXPECT_EQ(static_cast<int64_t>(started_at.size()), overlap.last_step().buckets);  // all, in the pass
  overlap.finish();
  EXPECT_EQ(overlap.last_step().started_in_backward, overlap.last_step().buckets);
  EXPECT_EQ(overlap.last_step().buckets, 3);
  for (size_t i = 1; i < started_at.size(); ++i) EXPECT_LT(started_at[i], started_at[i - 1]);
  const auto averaged = grads_of(params);
  for (size_t i = 0; i < plain.size(); ++i)
    EXPECT_TRUE(torch::equal(averaged[i], plain[i])) << "parameter " << i;
}

TEST(OverlappedAverage, AFailedSumIsThrownByFinishNotInsideAutograd) {
  Fixture f(/*with_unused=*/false);
  const auto params = f.net.params();
  auto& fused = f.fused;
  int waited = 0;
  OverlappedGradientAverage overlap(
      params, fused.offsets(), fused.flat_grad(), 2,
      [&](const torch::Tensor&) {
        return OverlappedGradientAverage::Wait([&] {
          ++waited;
          throw Error("the gradient all-reduce failed: a peer died");
        });
      },
      4 << 10);
  fused.zero_grad();
  overlap.arm();
  EXPECT_NO_THROW(f.loss(4).backward());
  EXPECT_THROW(overlap.finish(), Error);
  EXPECT_EQ(waited, overlap.last_step().buckets);  // every started sum waited for
  // The next step arms again.
  fused.zero_grad();
  overlap.arm();
  f.loss(5).backward();
  EXPECT_THROW(overlap.finish(), Error);
}

TEST(OverlappedAverage, RefusesParametersThatDoNotTileTheFlatGradient) {
  Fixture f;
  auto offsets = f.fused.offsets();
  offsets.back() += 1;
  EXPECT_THROW(OverlappedGradientAverage(f.net.params(), offsets, f.fused.flat_grad(), 2, f.fake_sum(2)),
               Error);
}

}  // namespace
}  // namespace dojo::train
