#include "models/keypoint_probe.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "core/checkpoint.h"
#include "core/state_dict.h"
#include "test_util.h"

namespace dojo::models {
namespace {

TEST(KeypointProbe, ShapesRangesAndCheckpointRoundTrip) {
  test::OneThread one;
  torch::manual_seed(0);
  KeypointProbeConfig c;
  c.size = 32;
  c.width = 8;
  KeypointProbe probe(c);
  const auto out = probe->forward(torch::rand({2, 3, 32, 32}));
  EXPECT_EQ(out.coords.sizes(), (std::vector<int64_t>{2, 6, 2}));
  EXPECT_EQ(out.presence.sizes(), (std::vector<int64_t>{2, 6}));
  EXPECT_GE(out.coords.min().item<float>(), 0.f);  // a soft-argmax stays inside the frame
  EXPECT_LE(out.coords.max().item<float>(), 1.f);
  EXPECT_EQ(keypoint_offset(c, "robot"), 0);
  EXPECT_EQ(keypoint_offset(c, "human"), 3);
  EXPECT_NE(test::error_message([&] { keypoint_offset(c, "dog"); }).find("dog"), std::string::npos);

  test::TempDir tmp;
  save_checkpoint(tmp / "p", keypoint_probe_checkpoint(*probe));
  auto loaded = load_keypoint_probe(tmp / "p");
  EXPECT_EQ(loaded->config().to_json(), c.to_json());
  const auto frames = torch::randint(0, 255, {3, 40, 48, 3}, torch::kUInt8);  // any size: cropped, resized
  const auto a = detect_keypoints(probe, frames), b = detect_keypoints(loaded, frames);
  EXPECT_TRUE(a.coords.equal(b.coords));
  EXPECT_TRUE(a.presence.equal(b.presence));
  EXPECT_NE(test::error_message([&] { load_keypoint_probe(tmp / "none"); }).find("none"), std::string::npos);
}

TEST(KeypointProbe, TargetsPutEachEmbodimentInItsSlots) {
  KeypointProbeConfig c;
  const auto kp = torch::rand({2, 3, 3});
  const auto t = probe_targets(c, {"robot", "human"}, kp);  // [2, 6, 3]
  EXPECT_TRUE(t[0].narrow(0, 0, 3).equal(kp[0]));
  EXPECT_EQ(t[0].narrow(0, 3, 3).abs().sum().item<float>(), 0.f);  // no hand in a robot frame
  EXPECT_TRUE(t[1].narrow(0, 3, 3).equal(kp[1]));
  EXPECT_EQ(t[1].narrow(0, 0, 3).abs().sum().item<float>(), 0.f);
}

TEST(KeypointProbe, ConfigErrorsNameTheField) {
  EXPECT_NE(test::error_message([] {
              KeypointProbeConfig::from_json({{"size", 30}});
            }).find("size"),
            std::string::npos);
  EXPECT_NE(test::error_message([] {
              KeypointProbeConfig::from_json({{"width", "wide"}});
            }).find("width"),
            std::string::npos);
}

}  // namespace
}  // namespace dojo::models
