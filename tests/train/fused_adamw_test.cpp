// The fused end of a training step against its reference: clip_grad_norm_, torch::optim::AdamW
// and diffusion::ema_update on the same weights and gradients; a resume through the saved
// optimizer state continuing exactly as an unbroken run; and the update sharded over ranks
// (ZeRO-1, here threads of one process) giving the unsharded one's bits.
#include "train/fused_adamw.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <condition_variable>
#include <mutex>
#include <thread>

#include "core/error.h"
#include "core/state_dict.h"
#include "diffusion/flow_matching.h"
#include "train/train_util.h"

namespace dojo::train {
namespace {

torch::nn::Sequential small_net() {
  return torch::nn::Sequential(torch::nn::Linear(7, 5), torch::nn::GELU(), torch::nn::Linear(5, 3));
}

void copy_weights(torch::nn::Module& to, const torch::nn::Module& from) {
  load_state_dict(to, state_dict(from));
}

double max_diff(const std::vector<torch::Tensor>& a, const std::vector<torch::Tensor>& b) {
  double worst = 0;
  for (size_t i = 0; i < a.size(); ++i) worst = std::max(worst, (a[i] - b[i]).abs().max().item<double>());
  return worst;
}

// Gradients of step k, the same for every copy (some steps large enough to be clipped).
void set_grads(const std::vector<torch::Tensor>& params, int64_t k) {
  auto gen = cpu_generator(100 + k);
  torch::NoGradGuard no_grad;
  for (const auto& p : params)
    p.mutable_grad().copy_(torch::randn(p.sizes(), gen) * (k % 2 == 0 ? 3.0 : 0.01));
}

TEST(FusedAdamW, MatchesClipAdamWAndEmaStepByStep) {
  torch::manual_seed(0);
  auto ref = small_net(), fused = small_net(), ref_ema = small_net(), fused_ema = small_net();
  for (auto* m : {&fused, &ref_ema, &fused_ema}) copy_weights(**m, *ref);
  const auto options = torch::optim::AdamWOptions(1e-2).weight_decay(0.1);
  torch::optim::AdamW ref_opt(ref->parameters(), options);
  torch::optim::AdamW fused_opt(fused->parameters(), options);
  const auto fused_params = fused->parameters();
  const auto* first = fused_params[0].unsafeGetTensorImpl();
  FusedAdamW flat(fused_opt, fused_params, fused_ema->parameters());
  EXPECT_EQ(fused->parameters()[0].unsafeGetTensorImpl(), first);  // the same tensors, now views
  for (auto& p : ref->parameters()) p.mutable_grad() = torch::zeros_like(p);
  auto ref_ema_params = ref_ema->parameters();
  for (int64_t k = 0; k < 6; ++k) {
    const double lr = 1e-2 * (k + 1) / 6.0, beta = diffusion::power_ema_beta(k + 1, 6.94);
    flat.zero_grad();
    set_grads(fused->parameters(), k);
    set_grads(ref->parameters(), k);
    const double ref_norm = torch::nn::utils::clip_grad_norm_(ref->parameters(), 0.5);
    static_cast<torch::optim::AdamWOptions&>(ref_opt.param_groups()[0].options()).lr(lr);
    ref_opt.step();
    diffusion::ema_update(ref_ema_params, ref->parameters(), beta);
    const double norm = flat.step(0.5, lr, beta);
    EXPECT_NEAR(norm, ref_norm, 1e-5 * ref_norm) << "step " << k;
    EXPECT_LT(max_diff(fused->parameters(), ref->parameters()), 1e-6) << "step " << k;
    EXPECT_LT(max_diff(fused_ema->parameters(), ref_ema_params), 1e-6) << "step " << k;
  }
  // The moments as the checkpoint sees them, through the optimizer's own state.
  const auto a = adamw_state(ref_opt, *ref), b = adamw_state(fused_opt, *fused);
  ASSERT_EQ(a.size(), b.size());
  for (size_t i = 0; i < a.size(); ++i) {
    EXPECT_EQ(a[i].first, b[i].first);
    EXPECT_LT((a[i].second.to(torch::kDouble) - b[i].second.to(torch::kDouble)).abs().max().item<double>(),
              1e-6)
        << a[i].first;
  }
}

TEST(FusedAdamW, ResumesFromTheSavedStateAsIfUnbroken) {
  torch::manual_seed(1);
  auto unbroken = small_net(), resumed = small_net();
  copy_weights(*resumed, *unbroken);
  const auto options = torch::optim::AdamWOptions(1e-2).weight_decay(0.1);
  torch::optim::AdamW opt(unbroken->parameters(), options);
  FusedAdamW flat(opt, unbroken->parameters());
  for (int64_t k = 0; k < 5; ++k) {
    if (k == 3) {
      // A resume at step 3: the weights and the saved moments into a fresh network and optimizer.
      copy_weights(*resumed, *unbroken);
      torch::optim::AdamW resumed_opt(resumed->parameters(), options);
      load_adamw_state(resumed_opt, *resumed, adamw_state(opt, *unbroken));
      FusedAdamW resumed_flat(resumed_opt, resumed->parameters());
      for (int64_t j = k; j < 5; ++j) {
        resumed_flat.zero_grad();
        set_grads(resumed->parameters(), j);
        resumed_flat.step(0.5, 1e-2, 0);
      }
    }
    flat.zero_grad();
    set_grads(unbroken->parameters(), k);
    flat.step(0.5, 1e-2, 0);
  }
  EXPECT_EQ(max_diff(resumed->parameters(), unbroken->parameters()), 0.0);
}

// Collectives between the threads of one process: each rank leaves a copy of its tensor, all
// wait, each reads what it needs, all wait again before the slots are reused.
class ThreadGroup {
 public:
  explicit ThreadGroup(int world) : world_(world), slots_(world) {}
  FusedAdamW::Collectives collectives(int rank) {
    FusedAdamW::Collectives c;
    c.rank = rank;
    c.world = world_;
    c.all_gather = [this, rank](const torch::Tensor& mine, const std::vector<torch::Tensor>& out) {
      exchange(rank, mine, out);
    };
    c.gather_to_main = [this, rank](const torch::Tensor& mine, const std::vector<torch::Tensor>& out) {
      EXPECT_EQ(out.size(), rank == 0 ? static_cast<size_t>(world_) : 0u);
      exchange(rank, mine, out);
    };
    return c;
  }

 private:
  void barrier() {
    std::unique_lock<std::mutex> lock(mutex_);
    const int64_t generation = generation_;
    if (++arrived_ == world_) {
      arrived_ = 0;
      ++generation_;
      wake_.notify_all();
    } else {
      wake_.wait(lock, [&] { return generation_ != generation; });
    }
  }
  void exchange(int rank, const torch::Tensor& mine, const std::vector<torch::Tensor>& out) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      slots_[rank] = mine.clone();
    }
    barrier();
    for (size_t r = 0; r < out.size(); ++r) out[r].copy_(slots_[r]);
    barrier();
  }
  int world_;
  std::vector<torch::Tensor> slots_;
  std::mutex mutex_;
  std::condition_variable wake_;
  int arrived_ = 0;
  int64_t generation_ = 0;
};

TEST(FusedAdamW, ShardedOverRanksGivesTheWholeUpdatesBits) {
  // 58 parameters: 3 ranks hold 20, 20 and a short 18; of 13 ranks the last holds none.
  for (const int world : {3, 13}) {
    torch::manual_seed(2);
    auto whole = small_net(), whole_ema = small_net();
    copy_weights(*whole_ema, *whole);
    const auto options = torch::optim::AdamWOptions(1e-2).weight_decay(0.1);
    constexpr int64_t kSteps = 5, kSaveAfter = 3;
    auto run = [&](torch::nn::Sequential net, torch::optim::AdamW& opt, FusedAdamW& flat,
                   NamedTensors& saved) {
      for (int64_t k = 0; k < kSteps; ++k) {
        flat.zero_grad();
        set_grads(net->parameters(), k);
        flat.step(0.5, 1e-2, diffusion::power_ema_beta(k + 1, 6.94));
        if (k + 1 == kSaveAfter) {
          flat.gather_state();  // every rank; rank 0's optimizer then holds the whole moments
          saved = adamw_state(opt, *net);
          for (auto& t : saved) t.second = t.second.clone();
        }
      }
    };
    // The ranks: copies of the same start, one thread each.
    std::vector<torch::nn::Sequential> nets, emas;
    std::vector<std::unique_ptr<torch::optim::AdamW>> opts;
    std::vector<std::unique_ptr<FusedAdamW>> flats;
    ThreadGroup group(world);
    for (int r = 0; r < world; ++r) {
      nets.push_back(small_net());
      emas.push_back(small_net());
      copy_weights(*nets.back(), *whole);
      copy_weights(*emas.back(), *whole);
      opts.push_back(std::make_unique<torch::optim::AdamW>(nets.back()->parameters(), options));
      flats.push_back(
          std::make_unique<FusedAdamW>(*opts.back(), nets.back()->parameters(), emas.back()->parameters()));
      flats.back()->shard(group.collectives(r));
    }
    std::vector<NamedTensors> saved(world);
    std::vector<std::thread> threads;
    for (int r = 0; r < world; ++r)
      threads.emplace_back([&, r] { run(nets[r], *opts[r], *flats[r], saved[r]); });
    for (auto& t : threads) t.join();
    torch::optim::AdamW whole_opt(whole->parameters(), options);
    FusedAdamW whole_flat(whole_opt, whole->parameters(), whole_ema->parameters());
    NamedTensors whole_saved;
    run(whole, whole_opt, whole_flat, whole_saved);

    for (int r = 0; r < world; ++r) {
      EXPECT_EQ(max_diff(nets[r]->parameters(), whole->parameters()), 0.0)
          << "world " << world << " rank " << r;
      EXPECT_EQ(max_diff(emas[r]->parameters(), whole_ema->parameters()), 0.0)
          << "world " << world << " rank " << r;
      EXPECT_LE(flats[r]->moment_elements(), 2 * ((58 + world - 1) / world))
          << "world " << world << " rank " << r;
    }
    // The checkpoint's moments, gathered on rank 0 only.
    ASSERT_EQ(saved[0].size(), whole_saved.size()) << "world " << world;
    for (size_t i = 0; i < whole_saved.size(); ++i) {
      EXPECT_EQ(saved[0][i].first, whole_saved[i].first);
      EXPECT_TRUE(torch::equal(saved[0][i].second, whole_saved[i].second)) << whole_saved[i].first;
    }
    EXPECT_TRUE(saved[1].empty()) << "only rank 0 receives the moments";
  }
}

TEST(FusedAdamW, RefusesAGradientThatWasReplaced) {
  auto net = small_net();
  torch::optim::AdamW opt(net->parameters(), torch::optim::AdamWOptions(1e-3));
  FusedAdamW flat(opt, net->parameters());
  net->parameters()[0].mutable_grad() = torch::zeros_like(net->parameters()[0]);
  EXPECT_THROW(flat.zero_grad(), Error);
}

}  // namespace
}  // namespace dojo::train
