#include "data/actions.h"

#include <ATen/CPUGeneratorImpl.h>
#include <torch/torch.h>

#include <nlohmann/json.hpp>

#include "core/error.h"
#include "test_util.h"

namespace dojo::data {

TEST(Actions, NormalizeMinMaxHandComputed) {
  ArrayStats stats;
  stats.min = {0.f, -2.f, 5.f};
  stats.max = {10.f, 2.f, 5.f};  // third dimension never moves
  const auto a = torch::tensor({{0.f, -2.f, 5.f}, {5.f, 0.f, 5.f}, {10.f, 1.f, 5.f}});
  const auto n = normalize_min_max(a, stats);
  const auto expected = torch::tensor({{-1.f, -1.f, 0.f}, {0.f, 0.f, 0.f}, {1.f, 0.5f, 0.f}});
  EXPECT_TRUE(torch::allclose(n, expected)) << n;
  // Inverse restores the moving dimensions; the constant one comes back as its value.
  EXPECT_TRUE(torch::allclose(denormalize_min_max(n, stats), a));
}

TEST(Actions, NormalizeRejectsWidthMismatch) {
  ArrayStats stats;
  stats.min = {0.f};
  stats.max = {1.f};
  EXPECT_THROW(normalize_min_max(torch::zeros({2, 3}), stats), Error);
}

TEST(Actions, ChunkRelativeHandComputed) {
  // 9 rows = baseline + 2 chunks of 4, one dimension, value = row index squared.
  auto a = torch::arange(9, torch::kFloat32).pow(2).unsqueeze(1);  // [9, 1]
  const auto d = chunk_relative(a, 4);
  // chunk 1 rows 1..4 relative to row 0 (0): 1, 4, 9, 16; chunk 2 rows 5..8 relative to row 4 (16).
  const auto expected = torch::tensor({1.f, 4.f, 9.f, 16.f, 9.f, 20.f, 33.f, 48.f}).unsqueeze(1);
  EXPECT_TRUE(torch::equal(d, expected)) << d;
}

TEST(Actions, ChunkRelativeTwelveActionsFromFourteenSteps) {
  const auto a = torch::randn({14, 7});
  const auto d = chunk_relative(a, 4);
  ASSERT_EQ(d.sizes(), (std::vector<int64_t>{12, 7}));
  // Row j uses baseline 4*(j/4): rows 0-3 -> 0, 4-7 -> 4, 8-11 -> 8 (input indices).
  for (int j = 0; j < 12; ++j) EXPECT_TRUE(torch::allclose(d[j], a[1 + j] - a[4 * (j / 4)])) << "row " << j;
  EXPECT_EQ(chunk_relative(torch::zeros({13, 2}), 4).size(0), 12);
  EXPECT_THROW(chunk_relative(torch::zeros({4, 2}), 4), Error);
}

TEST(Actions, PlaceInSlotAndHumanMask) {
  const auto d = torch::ones({12, 6});
  const auto v = place_in_slot(d, slots::kDojoSimRobot);
  ASSERT_EQ(v.sizes(), (std::vector<int64_t>{12, kUnifiedActionDim}));
  EXPECT_EQ(v.sum().item<float>(), 72.f);
  EXPECT_EQ(v.slice(1, 169, 175).sum().item<float>(), 72.f);
  EXPECT_THROW(place_in_slot(torch::ones({2, 40}), slots::kGr1), Error);
  const auto h = human_action_placeholder(12);
  EXPECT_EQ(h.slice(1, 352, 384).sum().item<float>(), 12.f * 32.f);
  EXPECT_EQ(h.slice(1, 0, 352).abs().sum().item<float>(), 0.f);
}

TEST(Actions, SlotsTileTheVectorWithoutOverlap) {
  int covered = 0;
  int last_end = 0;
  for (const auto& slot : all_slots()) {
    EXPECT_GE(slot.begin, last_end) << slot.name;
    last_end = slot.end;
    covered += slot.width();
  }
  EXPECT_EQ(last_end, kUnifiedActionDim);
  EXPECT_EQ(slot_by_name("latent").begin, 352);
  EXPECT_THROW(slot_by_name("nope"), Error);
}

TEST(Actions, StatsAccumulator) {
  StatsAccumulator acc;
  acc.add(torch::tensor({{1.f, 10.f}, {3.f, 10.f}}));
  acc.add(torch::tensor({{5.f, 10.f}}));
  const auto s = acc.finish();
  EXPECT_FLOAT_EQ(s.min[0], 1.f);
  EXPECT_FLOAT_EQ(s.max[0], 5.f);
  EXPECT_FLOAT_EQ(s.mean[0], 3.f);
  EXPECT_FLOAT_EQ(s.std[0], 2.f);  // sample std of {1, 3, 5}
  EXPECT_FLOAT_EQ(s.std[1], 0.f);
  const auto back = ArrayStats::from_json(s.to_json(), "test");
  EXPECT_EQ(back.max, s.max);
}

TEST(Actions, UnionRangeWidensEachDimension) {
  ArrayStats a, b;
  a.min = {0.f, -1.f};
  a.max = {1.f, 2.f};
  b.min = {-0.5f, 0.f};
  b.max = {0.5f, 3.f};
  const auto u = union_range(a, b);
  EXPECT_EQ(u.min, (std::vector<float>{-0.5f, -1.f}));
  EXPECT_EQ(u.max, (std::vector<float>{1.f, 3.f}));
  b.min.push_back(0.f);
  b.max.push_back(1.f);
  EXPECT_THROW(union_range(a, b), Error);
}

}  // namespace dojo::data

namespace dojo::data {
namespace {

// Chunk by chunk, a live stream of raw commands gives the rows the clip pipeline gives the
// whole recording.
TEST(ActionChunker, StreamEqualsTheClipPipeline) {
  ArrayStats stats;
  stats.min = {-2, 0, 5};
  stats.max = {2, 10, 5};  // the last dimension never moves
  auto g = at::make_generator<at::CPUGeneratorImpl>(3);
  const auto raw = torch::rand({13, 3}, g) * 4 - 2;  // baseline row + 12 commands
  const auto expected = place_in_slot(chunk_relative(normalize_min_max(raw, stats), 4), slots::kDojoSimRobot);
  ActionChunker chunker(slots::kDojoSimRobot, stats);
  chunker.set_baseline(raw[0]);
  for (int64_t k = 0; k < 3; ++k)
    EXPECT_TRUE(torch::allclose(chunker.push(raw.narrow(0, 1 + 4 * k, 4)), expected.narrow(0, 4 * k, 4)));
  EXPECT_THROW(chunker.push(torch::zeros({4, 2})), Error);
  const auto message = test::error_message([&] { chunker.push(torch::zeros({3, 3})); });
  EXPECT_NE(message.find("got shape [3, 3]"), std::string::npos) << message;  // says what came
  // No baseline: the first row is its own.
  chunker.reset();
  EXPECT_EQ(chunker.push(raw.narrow(0, 1, 4))[0].abs().sum().item<double>(), 0);
}

// The teacher's chunked sampler takes 12 rows a push: three model chunks, each relative to the
// row before it as in training, never all 12 to the row before the push.
TEST(ActionChunker, TwelveRowPushesAreThreeModelChunks) {
  ArrayStats stats;
  stats.min = {-2, 0};
  stats.max = {2, 10};
  auto g = at::make_generator<at::CPUGeneratorImpl>(5);
  const auto raw = torch::rand({25, 2}, g) * 4 - 2;  // baseline row + 24 commands
  const auto expected = place_in_slot(chunk_relative(normalize_min_max(raw, stats), 4), slots::kDojoSimRobot);
  ActionChunker chunker(slots::kDojoSimRobot, stats, 12);
  EXPECT_EQ(chunker.rows_per_push(), 12);
  chunker.set_baseline(raw[0]);
  for (int64_t k = 0; k < 2; ++k)
    EXPECT_TRUE(torch::allclose(chunker.push(raw.narrow(0, 1 + 12 * k, 12)), expected.narrow(0, 12 * k, 12)))
        << "push " << k;
  EXPECT_THROW(chunker.push(torch::zeros({4, 2})), Error);
  EXPECT_THROW(ActionChunker(slots::kDojoSimRobot, stats, 6), Error);  // not whole model chunks
}

TEST(ActionChunker, OneRecordedSlotGivesTheModelsChunker) {
  ArrayStats stats;
  stats.min = {-2, 0, 5};
  stats.max = {2, 10, 5};
  stats.mean = stats.std = {0, 0, 0};
  const nlohmann::json one = {{"dojosim_robot", stats.to_json()}};
  auto chunker = single_slot_chunker(one, "model actions", 4);
  ASSERT_TRUE(chunker.has_value());
  EXPECT_EQ(chunker->width(), 3);
  ActionChunker direct(slots::kDojoSimRobot, stats);
  const auto raw = torch::tensor({{1.f, 2.f, 5.f}, {0.f, 4.f, 5.f}, {-1.f, 6.f, 5.f}, {2.f, 8.f, 5.f}});
  EXPECT_TRUE(torch::equal(chunker->push(raw), direct.push(raw)));  // [4, 384] in the robot's slot
  // Several slots or none: raw commands would not say which embodiment they drive.
  EXPECT_FALSE(
      single_slot_chunker({{"dojosim_robot", stats.to_json()}, {"g1", stats.to_json()}}, "m").has_value());
  EXPECT_FALSE(single_slot_chunker(nlohmann::json::object(), "m").has_value());
  // A broken range is refused naming where it was read.
  try {
    single_slot_chunker({{"dojosim_robot", {{"min", {0}}}}}, "model actions");
    FAIL() << "a range without max was accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("model actions.dojosim_robot"), std::string::npos) << e.what();
  }
  EXPECT_THROW(single_slot_chunker({{"no_such_slot", stats.to_json()}}, "m"), Error);
}

}  // namespace
}  // namespace dojo::data
