#include "models/attention.h"

#include <torch/torch.h>

#include "test_util.h"

namespace dojo::models {

// A direct loop-based reference for one head, independent of matmul broadcasting.
static torch::Tensor naive(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v,
                           bool causal) {
  const int64_t lq = q.size(0), lk = k.size(0);
  auto out = torch::zeros({lq, v.size(1)});
  for (int64_t i = 0; i < lq; ++i) {
    auto s = (k.matmul(q[i]) / std::sqrt(static_cast<double>(q.size(1))));  // [Lk]
    if (causal)
      for (int64_t j = 0; j < lk; ++j)
        if (j > i + (lk - lq)) s[j] = -INFINITY;
    out[i] = torch::softmax(s, 0).matmul(v);
  }
  return out;
}

TEST(Attention, MathMatchesNaiveLoop) {
  torch::manual_seed(0);
  const auto q = torch::randn({5, 8}), k = torch::randn({7, 8}), v = torch::randn({7, 3});
  EXPECT_TRUE(torch::allclose(attention_math(q, k, v), naive(q, k, v, false), 1e-5, 1e-6));
  EXPECT_TRUE(torch::allclose(attention_math(q, k, v, std::nullopt, true), naive(q, k, v, true), 1e-5, 1e-6));
}

TEST(Attention, BoolMaskEqualsAdditiveMask) {
  torch::manual_seed(1);
  const auto q = torch::randn({2, 4, 6, 8}), k = torch::randn({2, 4, 6, 8}), v = torch::randn({2, 4, 6, 8});
  const auto keep = torch::rand({6, 6}).gt(0.3).logical_or(torch::eye(6).to(torch::kBool));
  const auto additive = torch::where(keep, torch::zeros({6, 6}), torch::full({6, 6}, -INFINITY));
  EXPECT_TRUE(torch::allclose(attention_math(q, k, v, keep), attention_math(q, k, v, additive), 1e-5, 1e-6));
}

TEST(Attention, AutoAgreesWithMath) {
  // On libtorch 2.x this compares the fused kernel with the math path; on 1.13 auto is math.
  torch::manual_seed(2);
  const auto q = torch::randn({2, 3, 5, 16}), k = torch::randn({2, 3, 9, 16}),
             v = torch::randn({2, 3, 9, 16});
  for (bool causal : {false, true}) {
    const auto a = attention(q, k, v, std::nullopt, causal);
    const auto b = attention_math(q, k, v, std::nullopt, causal);
    EXPECT_TRUE(torch::allclose(a, b, 1e-4, 1e-5)) << "causal=" << causal;
  }
  if (!fused_attention_available()) {
    EXPECT_THROW(attention(q, k, v, std::nullopt, false, std::nullopt, AttentionBackend::kFused),
                 std::exception);
  }
}

TEST(Attention, FusedAgreesWithMath_CUDA) {
  DOJO_REQUIRE_CUDA();
  if (!fused_attention_available()) GTEST_SKIP() << "libtorch < 2.0";
  torch::manual_seed(3);
  const auto opts = torch::TensorOptions().device(torch::kCUDA);
  const auto q = torch::randn({1, 4, 64, 64}, opts), k = torch::randn({1, 4, 80, 64}, opts),
             v = torch::randn({1, 4, 80, 64}, opts);
  const auto a = attention(q, k, v, std::nullopt, true, std::nullopt, AttentionBackend::kFused);
  const auto b = attention_math(q, k, v, std::nullopt, true);
  EXPECT_TRUE(torch::allclose(a, b, 1e-3, 1e-4));
}

}  // namespace dojo::models
