#include "data/clip_sampler.h"

#include <map>

#include "test_util.h"

namespace dojo::data {

TEST(ClipSampler, WindowLayout) {
  const auto w = make_window(5, 3, 13);
  ASSERT_EQ(w.steps.size(), 14u);
  EXPECT_EQ(w.steps.front(), 5);
  EXPECT_EQ(w.steps.back(), 5 + 13 * 3);
  const auto frames = w.frame_indices();
  ASSERT_EQ(frames.size(), 13u);
  EXPECT_EQ(frames.front(), 8);
}

TEST(ClipSampler, FitRule) {
  // 14 steps at stride 1 need frames 0..13: 14 frames.
  EXPECT_FALSE(window_fits(13, 1, 13));
  EXPECT_TRUE(window_fits(14, 1, 13));
  EXPECT_TRUE(window_fits(53, 4, 13));
  EXPECT_FALSE(window_fits(52, 4, 13));
}

TEST(ClipSampler, SamplesStayInBoundsAndCoverStrides) {
  ClipConfig config;
  std::mt19937_64 rng(7);
  std::map<int, int> seen;
  for (int i = 0; i < 2000; ++i) {
    const auto w = sample_window(60, config, rng);
    ASSERT_TRUE(w.has_value());
    EXPECT_GE(w->steps.front(), 0);
    EXPECT_LT(w->steps.back(), 60);
    ++seen[w->stride];
  }
  EXPECT_EQ(seen.size(), 4u);
  for (const auto& [stride, count] : seen) EXPECT_GT(count, 350) << stride;
}

TEST(ClipSampler, ShortEpisodesUseOnlyStridesThatFit) {
  ClipConfig config;
  std::mt19937_64 rng(1);
  for (int i = 0; i < 200; ++i) {
    const auto w = sample_window(30, config, rng);  // only strides 1 and 2 fit
    ASSERT_TRUE(w.has_value());
    EXPECT_LE(w->stride, 2);
  }
  EXPECT_FALSE(sample_window(13, config, rng).has_value());
}

TEST(ClipSampler, DeterministicForSeed) {
  ClipConfig config;
  std::mt19937_64 a(42), b(42);
  for (int i = 0; i < 50; ++i)
    EXPECT_EQ(sample_window(100, config, a)->steps, sample_window(100, config, b)->steps);
}

TEST(ClipSampler, AllWindows) {
  const auto windows = all_windows(30, 1, 13, 4);
  // starts 0, 4, 8, 12, 16 (16 + 13 = 29 < 30)
  ASSERT_EQ(windows.size(), 5u);
  EXPECT_EQ(windows.back().start, 16);
}

}  // namespace dojo::data
