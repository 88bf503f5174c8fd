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
  pred.presence[0][3] = 2.0;    // said present, but 4 px from the truth
  pred.presence[0][5] = 1.0;    // said present where it is: 0 px off
  auto truth = torch::zeros({2, 3, 3});
  truth.narrow(2, 0, 2).fill_(0.5);
  truth[0][0][2] = 1, truth[0][1][2] = 1, truth[0][2][2] = 1;  // frame 0: all three in view
  const auto s = score_keypoints(pred, 3, truth, 20, 40);
  ASSERT_EQ(s.error.size(), 2u);
  EXPECT_NEAR(s.error[0], 3.0, 1e-5);  // mean of 4, 5 and 0 px
  // The radius is 3 px at 64x64, here 3 * 20 / 64 = 0.94 px: only the point placed right counts.
  EXPECT_NEAR(detection_radius_px(20, 40), 0.9375, 1e-12);
  EXPECT_NEAR(s.detected[0], 1.0 / 3, 1e-12);
  EXPECT_NEAR(s.present[0], 2.0 / 3, 1e-12);  // presence alone would count the misplaced one too
  EXPECT_TRUE(std::isnan(s.error[1]));        // nothing in view
  EXPECT_TRUE(std::isnan(s.detected[1]));
  EXPECT_NEAR(nan_mean(s.error), 3.0, 1e-5);
  EXPECT_TRUE(std::isnan(nan_mean({std::nan(""), std::nan("")})));
}

}  // namespace
}  // namespace dojo::eval
