// `dojo data convert --video-format raw`: any dataset into episodes of raw frames, the format a
// build without video libraries reads (docs/data.md).
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <filesystem>
#include <nlohmann/json.hpp>

#include "data/episode_store.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo {
namespace {

TEST(RawFramesCli, ConvertWritesTheDecodedFramesExactlyAndChecksThem) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 2;
  g.frames = 12;
  g.video_format = data::VideoFormat::kMp4;
  test::write_synthetic_dataset(tmp / "mp4", g);
  const auto src = (tmp / "mp4").string(), dst = (tmp / "raw").string();
  auto r = test::run_dojo("data convert " + src + " " + dst + " --video-format raw");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(nlohmann::json::parse(test::read_file(tmp / "raw" / "info.json")).at("video_format"), "raw");
  const auto mp4 = data::EpisodeStore::open(tmp / "mp4"), raw = data::EpisodeStore::open(tmp / "raw");
  EXPECT_TRUE(std::filesystem::exists(raw.episode_dir(1) / "video.safetensors"));
  for (size_t i = 0; i < 2; ++i)
    EXPECT_TRUE(torch::equal(raw.load(i).frames, mp4.load(i).frames)) << "the mp4's pictures, kept exactly";
  r = test::run_dojo("data check " + dst);
  EXPECT_EQ(r.exit_code, 0) << r.output;

  // And back to mp4; LeRobot has no raw videos.
  r = test::run_dojo("data convert " + dst + " " + (tmp / "again").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(data::EpisodeStore::open(tmp / "again").episode_dir(0) / "video.mp4"));
  r = test::run_dojo("data convert " + src + " " + (tmp / "le").string() +
                     " --to lerobot --robot-type arm --video-format raw");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("--to lerobot writes mp4 videos"), std::string::npos) << r.output;
  r = test::run_dojo("data convert " + src + " " + (tmp / "x").string() + " --video-format webm");
  EXPECT_NE(r.exit_code, 0);
}

}  // namespace
}  // namespace dojo
