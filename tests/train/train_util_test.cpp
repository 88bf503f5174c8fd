#include "train/train_util.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/state_dict.h"
#include "test_util.h"

#include <cmath>

namespace dojo::train {
namespace {

// A plain AdamW loop saved after 3 steps and resumed continues exactly as the unbroken run.
TEST(TrainUtil, AdamwCheckpointsResumeExactly) {
  const auto batch = torch::randn({4, 3});
  const auto run_steps = [&](torch::nn::Linear& net, torch::optim::AdamW& opt, int n) {
    for (int i = 0; i < n; ++i) {
      opt.zero_grad();
      net(batch).pow(2).mean().backward();
      opt.step();
    }
  };
  const auto checkpoint = [](const torch::nn::Linear& net) {
    CheckpointData data;
    data.config = {{"model", "linear"}};
    for (const auto& [name, t] : state_dict(*net)) data.model.emplace_back("net." + name, t);
    return data;
  };
  torch::manual_seed(0);
  torch::nn::Linear a(3, 2);
  torch::optim::AdamW opt_a(a->parameters(), torch::optim::AdamWOptions(1e-2));
  run_steps(a, opt_a, 3);
  test::TempDir dir;
  save_with_adamw(dir / "ck", checkpoint(a), opt_a, *a, 3);
  run_steps(a, opt_a, 2);

  torch::manual_seed(1);  // other initial weights: the checkpoint must replace them
  torch::nn::Linear b(3, 2);
  torch::optim::AdamW opt_b(b->parameters(), torch::optim::AdamWOptions(1e-2));
  EXPECT_EQ(resume_with_adamw(dir / "ck", *b, "net.", opt_b), 3);
  run_steps(b, opt_b, 2);
  EXPECT_TRUE(torch::allclose(a->weight, b->weight, 0, 1e-7));
  EXPECT_TRUE(torch::allclose(a->bias, b->bias, 0, 1e-7));
}

// run_adamw_loop that crashes at step 6 (last saved at 4) and is run again ends where an unbroken
// run does: the batches come from (seed, step), the rate from the step, the moments from the
// checkpoint.
TEST(TrainUtil, AdamwLoopResumesExactlyWithItsSchedule) {
  test::OneThread one;
  const auto train = [](const std::filesystem::path& out, int64_t crash_at) {
    torch::manual_seed(0);
    torch::nn::Linear net(3, 2);
    AdamwLoop loop;
    loop.name = "test";
    loop.out = out;
    loop.prefix = "net.";
    loop.steps = 8;
    loop.save_every = 4;
    loop.lr = 1e-2;
    loop.warmup_steps = 3;
    loop.cosine = true;
    loop.seed = 7;
    loop.batch_size = 4;
    const auto checkpoint = [&] {
      CheckpointData data;
      data.config = {{"model", "linear"}};
      for (const auto& [name, t] : state_dict(*net)) data.model.emplace_back("net." + name, t);
      return data;
    };
    const auto run =
        run_adamw_loop(*net, loop, checkpoint, [&](const LoopStep& s, int64_t batch, torch::Generator& gen) {
          if (s.index == crash_at) throw std::runtime_error("crash");
          const auto x = torch::randn({batch, 3}, gen);
          return AdamwStep{(net(x) - 1).pow(2).mean(), batch, {}};
        });
    return std::make_pair(net->weight.detach().clone(), run);
  };
  test::TempDir tmp;
  const auto [whole, whole_run] = train(tmp / "whole", -1);
  EXPECT_THROW(train(tmp / "split", 6), std::runtime_error);
  const auto [resumed, resumed_run] = train(tmp / "split", -1);
  EXPECT_EQ(resumed_run.start_step, 4);
  EXPECT_EQ(resumed_run.end_step, 8);
  EXPECT_TRUE(torch::allclose(whole, resumed, 0, 1e-6)) << whole << resumed;
  // The curve has loss and lr columns.
  const auto curve = test::read_file(tmp / "whole" / "loss.csv");
  EXPECT_EQ(curve.substr(0, curve.find('\n')), "step,loss,lr");
  // A finished run asked again trains nothing and reports no loss.
  const auto [again, again_run] = train(tmp / "whole", -1);
  EXPECT_TRUE(std::isnan(again_run.loss));
  EXPECT_TRUE(torch::equal(again, whole));
}

}  // namespace
}  // namespace dojo::train

namespace dojo::train {
namespace {

// Shares of each dataset in `draws` draws of a mixture over datasets of `sizes` clips.
std::vector<double> drawn_shares(const MixtureIndex& mixture, const std::vector<int64_t>& sizes,
                                 int64_t draws) {
  auto gen = step_generator(7, 0);
  const auto idx = mixture.draw(draws, gen);
  std::vector<double> shares(sizes.size(), 0);
  int64_t offset = 0;
  for (size_t d = 0; d < sizes.size(); ++d) {
    shares[d] = idx.ge(offset).logical_and(idx.lt(offset + sizes[d])).sum().item<double>() / draws;
    offset += sizes[d];
  }
  EXPECT_EQ(idx.min().item<int64_t>() >= 0 && idx.max().item<int64_t>() < offset, true);
  return shares;
}

TEST(MixtureIndex, WeightsSetEachDatasetsShareWhateverItsSize) {
  // 1:2:10, the paper's pretraining recipe, over datasets whose clip counts run the other way.
  const std::vector<int64_t> sizes = {5000, 300, 40};
  const MixtureIndex mixture(sizes, {1, 2, 10});
  const auto shares = drawn_shares(mixture, sizes, 20000);
  EXPECT_NEAR(shares[0], 1.0 / 13, 0.01);
  EXPECT_NEAR(shares[1], 2.0 / 13, 0.01);
  EXPECT_NEAR(shares[2], 10.0 / 13, 0.01);
  EXPECT_NEAR(mixture.shares()[2], 10.0 / 13, 1e-12);
  const auto record = mixture.record({"inhouse", "egodex", "hv"});
  ASSERT_EQ(record.size(), 3u);
  EXPECT_EQ(record[2].at("data"), "hv");
  EXPECT_EQ(record[2].at("clips"), 40);
  EXPECT_EQ(record[2].at("weight"), 10.0);
  EXPECT_NEAR(record[1].at("share").get<double>(), 2.0 / 13, 1e-12);
  // Every clip of the small dataset is reached.
  auto gen = step_generator(3, 0);
  const auto idx = mixture.draw(4000, gen);
  auto seen = torch::zeros({5340}, torch::kBool);
  seen.index_put_({idx}, true);
  EXPECT_TRUE(seen.narrow(0, 5300, 40).all().item<bool>());
}

TEST(MixtureIndex, WithoutWeightsEveryClipIsAlike) {
  const std::vector<int64_t> sizes = {900, 100};
  const MixtureIndex mixture(sizes);
  EXPECT_FALSE(mixture.weighted());
  const auto shares = drawn_shares(mixture, sizes, 20000);
  EXPECT_NEAR(shares[0], 0.9, 0.01);
  EXPECT_NEAR(mixture.shares()[1], 0.1, 1e-12);
  EXPECT_TRUE(mixture.record({"a", "b"})[0].at("weight").is_null());
  // The unweighted stream is the one trainers drew before weights existed.
  auto a = step_generator(5, 2), b = step_generator(5, 2);
  EXPECT_TRUE(torch::equal(mixture.draw(8, a), torch::randint(1000, {8}, b, torch::kLong)));
}

TEST(MixtureIndex, SameGeneratorSameDrawsAndBadWeightsRefused) {
  const MixtureIndex mixture({10, 10}, {1, 3});
  auto a = step_generator(1, 9), b = step_generator(1, 9);
  EXPECT_TRUE(torch::equal(mixture.draw(64, a), mixture.draw(64, b)));
  EXPECT_THROW(MixtureIndex({10, 10}, {1}), Error);
  EXPECT_THROW(MixtureIndex({10, 10}, {1, 0}), Error);
  EXPECT_THROW(MixtureIndex({10, 0}, {1, 1}), Error);
}

}  // namespace
}  // namespace dojo::train
