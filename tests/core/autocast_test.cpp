#include "core/autocast.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <stdexcept>

#include "core/error.h"
#include "test_util.h"

namespace dojo {
namespace {

TEST(Autocast, ParsesPrecisionsWithAClearError) {
  for (const auto p : {Precision::kFloat32, Precision::kBFloat16, Precision::kFloat16})
    EXPECT_EQ(parse_precision(to_string(p)), p);
  EXPECT_EQ(to_string(Precision::kBFloat16), "bf16");
  EXPECT_EQ(autocast_dtype(Precision::kBFloat16), torch::kBFloat16);
  EXPECT_EQ(autocast_dtype(Precision::kFloat16), torch::kHalf);
  EXPECT_EQ(autocast_dtype(Precision::kFloat32), torch::kFloat32);
  EXPECT_THROW(parse_precision("fp8"), UsageError);
  EXPECT_NE(test::error_message([] { parse_precision("fp8"); }).find("'fp8'"), std::string::npos);
  // libtorch's CPU autocast knows bf16 only; fp16 is for CUDA.
  EXPECT_THROW(check_precision_supported(Precision::kFloat16, torch::kCPU), UsageError);
  EXPECT_NO_THROW(check_precision_supported(Precision::kFloat16, torch::kCUDA));
  EXPECT_NO_THROW(check_precision_supported(Precision::kBFloat16, torch::kCPU));
}

TEST(Autocast, GuardTurnsCpuAutocastOnAndRestoresItWhenNested) {
  torch::manual_seed(0);  // fixed inputs: the bf16 error below depends on the draw
  const auto a = torch::randn({8, 32}), b = torch::randn({32, 4});
  const auto exact = torch::matmul(a, b);
  ASSERT_FALSE(AutocastGuard::is_enabled(torch::kCPU));
  const auto outside_dtype = AutocastGuard::dtype(torch::kCPU);
  EXPECT_EQ(exact.scalar_type(), torch::kFloat32);
  {
    AutocastGuard bf16(torch::kCPU, Precision::kBFloat16);
    EXPECT_TRUE(AutocastGuard::is_enabled(torch::kCPU));
    EXPECT_FALSE(AutocastGuard::is_enabled(torch::kCUDA));  // one device type at a time
    EXPECT_EQ(AutocastGuard::dtype(torch::kCPU), torch::kBFloat16);
    const auto low = torch::matmul(a, b);
    EXPECT_EQ(low.scalar_type(), torch::kBFloat16);
    // bf16 keeps 8 significant bits (unit roundoff 2^-8 = 0.0039): the inputs and the output are
    // each rounded once, so the relative error is a few roundoffs, not fp32's 1e-7. An unseeded
    // draw once reached 0.0115; the bound is 5 roundoffs.
    EXPECT_LT(((low.to(torch::kFloat32) - exact).norm() / exact.norm()).item<double>(), 5.0 / 256);
    {
      // fp32 = enabled false: autocast off inside an autocast region, as torch.autocast(enabled=False).
      AutocastGuard off(torch::kCPU, Precision::kFloat32);
      EXPECT_FALSE(AutocastGuard::is_enabled(torch::kCPU));
      EXPECT_EQ(torch::matmul(a, b).scalar_type(), torch::kFloat32);
      {
        AutocastGuard again(torch::kCPU, torch::kBFloat16);
        EXPECT_TRUE(AutocastGuard::is_enabled(torch::kCPU));
        EXPECT_EQ(torch::matmul(a, b).scalar_type(), torch::kBFloat16);
      }
      EXPECT_FALSE(AutocastGuard::is_enabled(torch::kCPU));
      EXPECT_EQ(torch::matmul(a, b).scalar_type(), torch::kFloat32);
    }
    EXPECT_TRUE(AutocastGuard::is_enabled(torch::kCPU));
    EXPECT_EQ(AutocastGuard::dtype(torch::kCPU), torch::kBFloat16);
    EXPECT_EQ(torch::matmul(a, b).scalar_type(), torch::kBFloat16);
  }
  EXPECT_FALSE(AutocastGuard::is_enabled(torch::kCPU));
  EXPECT_EQ(AutocastGuard::dtype(torch::kCPU), outside_dtype);
  EXPECT_EQ(torch::matmul(a, b).scalar_type(), torch::kFloat32);
}

TEST(Autocast, CudaGuardLeavesCpuOpsAloneAndStateComesBackOnThrow) {
  const auto a = torch::randn({4, 8}), b = torch::randn({8, 4});
  {
    AutocastGuard cuda(torch::kCUDA, torch::kHalf);  // only a flag: no GPU is touched
    EXPECT_TRUE(AutocastGuard::is_enabled(torch::kCUDA));
    EXPECT_EQ(AutocastGuard::dtype(torch::kCUDA), torch::kHalf);
    EXPECT_FALSE(AutocastGuard::is_enabled(torch::kCPU));
    EXPECT_EQ(torch::matmul(a, b).scalar_type(), torch::kFloat32);
  }
  EXPECT_FALSE(AutocastGuard::is_enabled(torch::kCUDA));

  try {
    AutocastGuard bf16(torch::kCPU, torch::kBFloat16);
    throw std::runtime_error("unwind");
  } catch (const std::runtime_error&) {
  }
  EXPECT_FALSE(AutocastGuard::is_enabled(torch::kCPU));

  // A bad request throws before changing anything.
  EXPECT_THROW(AutocastGuard(torch::kCPU, torch::kFloat32, /*enabled=*/true), Error);
  EXPECT_THROW(AutocastGuard(torch::kCPU, torch::kHalf), Error);  // CPU autocast is bf16 only
  EXPECT_THROW(AutocastGuard(c10::DeviceType::Meta, torch::kBFloat16), Error);
  EXPECT_FALSE(AutocastGuard::is_enabled(torch::kCPU));
  EXPECT_EQ(torch::matmul(a, b).scalar_type(), torch::kFloat32);
}

}  // namespace
}  // namespace dojo
