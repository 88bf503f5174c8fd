// The census of matrix products: what it counts (operators, layouts, the backward pass), what it
// does not (nested products, other operators), and the roofline it times from them.
#include "core/gemm_census.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <nlohmann/json.hpp>
#include <thread>

#include "test_util.h"

namespace dojo {
namespace {

const GemmRecord* find(const std::vector<GemmRecord>& records, GemmShape shape) {
  for (const auto& r : records)
    if (r.shape == shape) return &r;
  return nullptr;
}

GemmShape shape(int64_t batch, int64_t m, int64_t k, int64_t n, bool a_t = false, bool b_t = false) {
  GemmShape s;
  s.batch = batch;
  s.m = m;
  s.k = k;
  s.n = n;
  s.a_transposed = a_t;
  s.b_transposed = b_t;
  return s;
}

TEST(GemmCensus, CountsEachProductOnceWithItsLayout) {
  test::OneThread one_thread;
  torch::NoGradGuard no_grad;
  const auto a = torch::randn({6, 5}), b = torch::randn({5, 7});
  std::vector<GemmRecord> records;
  {
    GemmCensus census;
    torch::mm(a, b);
    torch::mm(a, b);
    torch::mm(a, torch::randn({7, 5}).t());  // a transposed view: BLAS's "T"
    torch::nn::functional::linear(a, torch::randn({3, 5}), torch::randn({3}));  // addmm under linear
    torch::bmm(torch::randn({4, 6, 5}), torch::randn({4, 5, 2}));
    torch::matmul(torch::randn({2, 3, 6, 5}), torch::randn({2, 3, 5, 2}));  // matmul → bmm, counted once
    (void)(a + 1).sum();                                                    // not a product
    records = census.records();
  }
  const auto* plain = find(records, shape(1, 6, 5, 7));
  ASSERT_NE(plain, nullptr);
  EXPECT_EQ(plain->calls, 2);
  EXPECT_GT(plain->seconds_in_place, 0);
  const auto* transposed = find(records, shape(1, 6, 5, 7, false, true));
  ASSERT_NE(transposed, nullptr);
  EXPECT_EQ(transposed->calls, 1);
  const auto* linear = find(records, shape(1, 6, 5, 3, false, true));  // x · Wᵀ
  ASSERT_NE(linear, nullptr);
  EXPECT_EQ(linear->calls, 1);
  const auto* batched = find(records, shape(4, 6, 5, 2));
  ASSERT_NE(batched, nullptr);
  EXPECT_EQ(batched->calls, 1);
  const auto* from_matmul = find(records, shape(6, 6, 5, 2));
  ASSERT_NE(from_matmul, nullptr);
  EXPECT_EQ(from_matmul->calls, 1);
  int64_t calls = 0;
  for (const auto& r : records) calls += r.calls;
  EXPECT_EQ(calls, 6);
  // Largest total FLOPs first.
  for (size_t i = 1; i < records.size(); ++i)
    EXPECT_GE(records[i - 1].shape.flops() * static_cast<double>(records[i - 1].calls),
              records[i].shape.flops() * static_cast<double>(records[i].calls));
}

TEST(GemmCensus, CountsTheBackwardPassProducts) {
  test::OneThread one_thread;
  const auto x = torch::randn({8, 5}, torch::requires_grad());
  const auto w = torch::randn({3, 5}, torch::requires_grad());
  GemmCensus census;
  torch::nn::functional::linear(x, w).pow(2).sum().backward();
  const auto records = census.records();
  int64_t calls = 0;
  for (const auto& r : records) calls += r.calls;
  EXPECT_EQ(calls, 3);  // forward, the input's gradient, the weight's gradient
  double flops = 0;
  for (const auto& r : records) flops += r.shape.flops() * static_cast<double>(r.calls);
  EXPECT_DOUBLE_EQ(flops, 3 * 2.0 * 8 * 5 * 3);
}

TEST(GemmCensus, CountsItsOwnThreadNotOthers) {
  test::OneThread one_thread;
  torch::NoGradGuard no_grad;
  const auto a = torch::randn({6, 5}), b = torch::randn({5, 7});
  GemmCensus census;
  std::thread other([&] { (void)torch::mm(a, b); });  // a data loader's product, say
  other.join();
  EXPECT_TRUE(census.records().empty());
  (void)torch::mm(a, b);
  EXPECT_EQ(census.records().size(), 1u);
}

TEST(GemmCensus, OneAtATime) {
  GemmCensus first;
  EXPECT_THROW(GemmCensus second, std::exception);
}

TEST(GemmCensus, TimesTheRecordedProductsAlone) {
  test::OneThread one_thread;
  std::vector<GemmRecord> records;
  {
    torch::NoGradGuard no_grad;
    GemmCensus census;
    const auto a = torch::randn({64, 32}), b = torch::randn({32, 48});
    for (int i = 0; i < 3; ++i) torch::mm(a, b);
    torch::bmm(torch::randn({2, 16, 8}), torch::randn({2, 8, 4}));
    records = census.records();
  }
  const auto roofline = time_alone(records, 2);
  EXPECT_EQ(roofline.calls, 4);
  EXPECT_DOUBLE_EQ(roofline.flops, 3 * 2.0 * 64 * 32 * 48 + 2.0 * 2 * 16 * 8 * 4);
  ASSERT_EQ(roofline.seconds_alone_each.size(), records.size());
  EXPECT_GT(roofline.seconds_alone, 0);
  EXPECT_GT(roofline.gflops_alone(), 0);
  EXPECT_DOUBLE_EQ(roofline.fraction_of(2 * roofline.seconds_alone), 0.5);
  const auto j = roofline.to_json(roofline.seconds_alone, records, 1);
  EXPECT_DOUBLE_EQ(j["fraction_of_roofline"].get<double>(), 1.0);
  ASSERT_EQ(j["shapes"].size(), 1u);
  EXPECT_EQ(j["shapes"][0]["calls"].get<int64_t>(), records[0].calls);
  EXPECT_THROW(time_alone(records, 0), std::exception);
}

}  // namespace
}  // namespace dojo
