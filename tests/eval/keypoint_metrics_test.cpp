#include "eval/keypoint_metrics.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cmath>

namespace dojo::eval {
namespace {

TEST(KeypointMetrics, ErrorAndDetectionByHand) {
  // Two frames of a 3-keypoint embodiment at slots 3..5 of a 6-keypoint probe, on 20 x 40 frames.
  models::KeypointOutput pred;
  pred.coords = torch::full({2, 6, 2}, 0.5);
  pred.presence = torch::full({2, 6}, -1.0);
  pred.coords[0][3][0] = 0.6;   // 0.1 of 40 px wide: 4 px off in u
  pred.coords[0][4][1] = 0.25;  // 0.25 of 20 px tall: 5 px off in v
  pred.presence[0][3] = 2.0;    // found
  auto truth = torch::zeros({2, 3, 3});
  truth.narrow(2, 0, 2).fill_(0.5);
  truth[0][0][2] = 1, truth[0][1][2] = 1;  // frame 0: keypoints 0 and 1 in view
  const auto s = score_keypoints(pred, 3, truth, 20, 40);
  ASSERT_EQ(s.error.size(), 2u);
  EXPECT_NEAR(s.error[0], 4.5, 1e-5);    // mean of 4 and 5 px
  EXPECT_DOUBLE_EQ(s.detected[0], 0.5);  // one of the two found
  EXPECT_TRUE(std::isnan(s.error[1]));   // nothing in view
  EXPECT_NEAR(nan_mean(s.error), 4.5, 1e-5);
  EXPECT_TRUE(std::isnan(nan_mean({std::nan(""), std::nan("")})));
}

}  // namespace
}  // namespace dojo::eval
