// The pieces of data parallelism that need no second process: how a step's batch splits into
// micro-batches, which stream indices each rank draws, and the environment torchrun sets.
#include "train/data_parallel.h"

#include <gtest/gtest.h>

#include <cstdlib>
#include <set>

#include "core/error.h"
#include "data/clip_loader.h"
#include "test_util.h"

namespace dojo::train {
namespace {

BatchShards shards_of(int64_t batch, int64_t accumulate, int64_t world, int64_t rank) {
  BatchShards s;
  s.global_batch = batch;
  s.accumulate = accumulate;
  s.world = world;
  s.rank = rank;
  s.micro_batch = batch / s.shards();
  return s;
}

TEST(DataParallel, OneProcessWithOneMicroBatchDrawsStepKFromStreamK) {
  const auto one = shards_of(8, 1, 1, 0);
  for (int64_t k : {0, 1, 7, 1000}) EXPECT_EQ(one.stream_index(k, 0), k);
  EXPECT_EQ(one.row_offset(0), 0);
  EXPECT_EQ(one.micro_batch, 8);
}

TEST(DataParallel, TwoProcessesDrawWhatOneProcessDrawsWithTwoMicroBatches) {
  const auto alone = shards_of(8, 2, 1, 0);
  const auto rank0 = shards_of(8, 1, 2, 0), rank1 = shards_of(8, 1, 2, 1);
  for (int64_t k = 0; k < 5; ++k) {
    EXPECT_EQ(rank0.stream_index(k, 0), alone.stream_index(k, 0));
    EXPECT_EQ(rank1.stream_index(k, 0), alone.stream_index(k, 1));
  }
  EXPECT_EQ(rank1.row_offset(0), alone.row_offset(1));
  // Every stream index is drawn exactly once over the ranks, steps and micro-batches.
  std::set<int64_t> seen;
  for (int64_t rank = 0; rank < 3; ++rank)
    for (int64_t k = 0; k < 4; ++k)
      for (int64_t j = 0; j < 2; ++j)
        EXPECT_TRUE(seen.insert(shards_of(12, 2, 3, rank).stream_index(k, j)).second);
  EXPECT_EQ(*seen.rbegin(), 4 * 6 - 1);
}

TEST(DataParallel, ABatchThatDoesNotSplitIsRefusedNamingTheFlags) {
  const auto& alone = data_parallel();  // no WORLD_SIZE in the test environment: a world of 1
  ASSERT_FALSE(alone.active());
  EXPECT_EQ(BatchShards::plan(6, 3, alone, "wm train").micro_batch, 2);
  const auto message = test::error_message([&] { BatchShards::plan(6, 4, alone, "wm train"); });
  EXPECT_NE(message.find("wm train: a batch of 6 does not split into 4 equal micro-batches"),
            std::string::npos)
      << message;
  EXPECT_NE(test::error_message([&] { BatchShards::plan(4, 0, alone, "x"); }).find("--accumulate"),
            std::string::npos);
}

TEST(DataParallel, TheEnvironmentIsReadAsTorchrunWritesItAndBadValuesAreNamed) {
  setenv("WORLD_SIZE", "4", 1);
  setenv("RANK", "3", 1);
  setenv("LOCAL_RANK", "1", 1);
  setenv("MASTER_ADDR", "10.0.0.2", 1);
  setenv("MASTER_PORT", "29999", 1);
  auto w = parallel_world_from_environment();
  EXPECT_EQ(w.world, 4);
  EXPECT_EQ(w.rank, 3);
  EXPECT_EQ(w.local_rank, 1);
  EXPECT_EQ(w.master_addr, "10.0.0.2");
  EXPECT_EQ(w.master_port, 29999);
  EXPECT_TRUE(w.overlap_backward);
  setenv("DOJO_DIST_OVERLAP", "0", 1);
  EXPECT_FALSE(parallel_world_from_environment().overlap_backward);
  setenv("DOJO_DIST_OVERLAP", "off", 1);
  EXPECT_NE(test::error_message([] { parallel_world_from_environment(); }).find("DOJO_DIST_OVERLAP=off"),
            std::string::npos);
  unsetenv("DOJO_DIST_OVERLAP");
  setenv("RANK", "4", 1);
  EXPECT_NE(test::error_message([] { parallel_world_from_environment(); }).find("RANK=4"), std::string::npos);
  setenv("RANK", "0", 1);
  setenv("MASTER_PORT", "http", 1);
  EXPECT_NE(test::error_message([] { parallel_world_from_environment(); }).find("MASTER_PORT=http"),
            std::string::npos);
  for (const char* name : {"WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"}) unsetenv(name);
  w = parallel_world_from_environment();
  EXPECT_EQ(w.world, 1);
  EXPECT_EQ(w.rank, 0);
  setenv("RANK", "3", 1);  // without WORLD_SIZE: one process, whatever else set RANK
  EXPECT_EQ(parallel_world_from_environment().world, 1);
  unsetenv("RANK");
}

TEST(DataParallel, ALoaderShareHandsOutItsRunsOfTheWholeStream) {
  data::LoaderOptions all;
  EXPECT_EQ(all.stream_index(5), 5);
  data::LoaderOptions share;  // rank 1 of 2 with 2 micro-batches a step: batches 2, 3, 6, 7, ...
  share.stream_every = 4;
  share.stream_first = 2;
  share.stream_run = 2;
  const std::vector<int64_t> expected = {2, 3, 6, 7, 10, 11};
  for (int64_t n = 0; n < 6; ++n) EXPECT_EQ(share.stream_index(n), expected[static_cast<size_t>(n)]);
}

}  // namespace
}  // namespace dojo::train
