#include "data/episode_store.h"

#include <torch/torch.h>

#include <fstream>

#include "core/error.h"
#include "core/safetensors.h"
#include "data/episode_source.h"
#include "test_util.h"

namespace dojo::data {
namespace {

// Frames with large smooth structure (codec-friendly) that change over time.
torch::Tensor moving_frames(int64_t t, int64_t h = 32, int64_t w = 32) {
  auto ti = torch::arange(t).view({t, 1, 1, 1});
  auto y = torch::arange(h).view({1, h, 1, 1});
  auto x = torch::arange(w).view({1, 1, w, 1});
  // Smooth ramps without wrap-around edges: what a codec reproduces well.
  const auto base = (x * 3 + y * 2 + ti * 2 + 20).to(torch::kFloat32);                        // [T, H, W, 1]
  return torch::cat({base, base * 0.8 + 20, 255 - base}, 3).clamp(0, 255).to(torch::kUInt8);  // [T, H, W, 3]
}

// A two-episode robot dataset whose action dim 0 equals the frame index.
std::filesystem::path make_robot_dataset(const std::filesystem::path& dir, int64_t frames = 20,
                                         VideoFormat format = VideoFormat::kMp4) {
  DatasetInfo info;
  info.name = "toy";
  info.embodiment = Embodiment::kRobot;
  info.action_slot = "dojosim_robot";
  info.fps = 10;
  info.height = info.width = 32;
  info.action_dim = 2;
  info.state_dim = 2;
  StatsAccumulator acc;
  for (int e = 0; e < 2; ++e) {
    EpisodeData ep;
    ep.frames = moving_frames(frames);
    ep.actions =
        torch::stack({torch::arange(frames).to(torch::kFloat32), torch::full({frames}, 3.f)}, 1);  // [T, 2]
    ep.states = ep.actions.clone();
    ep.meta = {{"task", "toy task"}};
    char id[16];
    std::snprintf(id, sizeof id, "%06d", e);
    write_episode(dir / "episodes" / id, ep, 10.0, format);
    acc.add(ep.actions);
    info.episodes.push_back({id, frames, e == 0 ? "train" : "val", "toy task"});
  }
  info.action_stats = acc.finish();
  info.state_stats = acc.finish();
  info.video_format = format;
  write_dataset_info(dir, info);
  return dir;
}

}  // namespace

TEST(EpisodeStore, WriteThenReadBack) {
  test::TempDir tmp;
  make_robot_dataset(tmp.path());
  const auto store = EpisodeStore::open(tmp.path());
  ASSERT_EQ(store.size(), 2u);
  EXPECT_EQ(store.info().total_frames(), 40);
  EXPECT_EQ(store.split_indices("val"), std::vector<size_t>{1});
  const auto ep = store.load(0);
  ASSERT_EQ(ep.frames.sizes(), (std::vector<int64_t>{20, 32, 32, 3}));
  // H.264 is lossy: compare with PSNR.
  const auto diff = ep.frames.to(torch::kFloat32) - moving_frames(20).to(torch::kFloat32);
  const double mse = diff.pow(2).mean().item<double>();
  EXPECT_GT(10 * std::log10(255.0 * 255.0 / std::max(mse, 1e-9)), 30.0);
  EXPECT_TRUE(torch::equal(ep.actions.select(1, 0), torch::arange(20).to(torch::kFloat32)));
  EXPECT_EQ(ep.meta["task"], "toy task");
  EXPECT_EQ(ep.meta["frames"], 20);
  EXPECT_EQ(store.check_episode(0), "");
}

TEST(EpisodeStore, RawFramesReadBackExactlyWithoutAVideoFile) {
  test::TempDir tmp;
  make_robot_dataset(tmp.path(), 20, VideoFormat::kRaw);
  EXPECT_EQ(nlohmann::json::parse(test::read_file(tmp / "info.json")).at("video_format"), "raw");
  const auto store = EpisodeStore::open(tmp.path());
  EXPECT_EQ(store.info().video_format, VideoFormat::kRaw);
  EXPECT_EQ(store.video_path(0).filename(), "video.safetensors");
  EXPECT_FALSE(std::filesystem::exists(store.episode_dir(0) / "video.mp4"));
  const auto frames = moving_frames(20);
  EXPECT_TRUE(torch::equal(store.load(0).frames, frames)) << "raw frames are the frames, not a lossy copy";
  EXPECT_EQ(store.check_episode(1), "");
  // The loaders' path: frames by index, in the order asked, through the dataset source.
  const auto source = open_dataset(tmp.path());
  EXPECT_TRUE(
      torch::equal(source->read_frames(0, {5, 2, 5}), frames.index_select(0, torch::tensor({5, 2, 5}))));
  auto message = test::error_message([&] { read_video_frames(store.video_path(0), {3, 20}); });
  EXPECT_NE(message.find("video.safetensors: frame 20 out of range (20 frames)"), std::string::npos)
      << message;
  // A file short of the listed frames, and a format nobody knows, are named.
  save_safetensors(store.video_path(0), {{"frames", frames.narrow(0, 0, 19).contiguous()}});
  message = store.check_episode(0);
  EXPECT_NE(message.find("video.safetensors: video has 19 frames, the dataset lists 20"), std::string::npos)
      << message;
  auto j = nlohmann::json::parse(test::read_file(tmp / "info.json"));
  j["video_format"] = "webm";
  std::ofstream(tmp / "info.json") << j.dump();
  message = test::error_message([&] { EpisodeStore::open(tmp.path()); });
  EXPECT_NE(message.find("field 'video_format': unknown video format 'webm'"), std::string::npos) << message;
}

TEST(EpisodeStore, InfoRoundTrip) {
  test::TempDir tmp;
  make_robot_dataset(tmp.path());
  const auto a = EpisodeStore::open(tmp.path()).info();
  const auto b = DatasetInfo::from_json(a.to_json(), "x");
  EXPECT_EQ(a.to_json(), b.to_json());
  EXPECT_EQ(b.action_stats->max[0], 19.f);
}

TEST(EpisodeStore, MissingDatasetNamesDirectory) {
  const auto message = test::error_message([] { EpisodeStore::open("/nonexistent/dataset"); });
  EXPECT_NE(message.find("/nonexistent/dataset"), std::string::npos) << message;
}

TEST(EpisodeStore, UnknownEmbodimentIsRejected) {
  test::TempDir tmp;
  make_robot_dataset(tmp.path());
  auto j = nlohmann::json::parse(test::read_file(tmp / "info.json"));
  j["embodiment"] = "octopus";
  std::ofstream(tmp / "info.json") << j.dump();
  const auto message = test::error_message([&] { EpisodeStore::open(tmp.path()); });
  EXPECT_NE(message.find("octopus"), std::string::npos) << message;
  EXPECT_NE(message.find("info.json"), std::string::npos) << message;
}

TEST(EpisodeStore, BadEpisodesNameTheEpisode) {
  test::TempDir tmp;
  make_robot_dataset(tmp.path());
  const auto store = EpisodeStore::open(tmp.path());
  const auto ep_dir = store.episode_dir(1);

  // Actions shorter than the frame count.
  save_safetensors(ep_dir / "data.safetensors",
                   {{"action", torch::zeros({5, 2})}, {"state", torch::zeros({20, 2})}});
  auto message = store.check_episode(1);
  EXPECT_NE(message.find("000001"), std::string::npos) << message;
  EXPECT_NE(message.find("rows"), std::string::npos) << message;

  // NaN in the actions.
  auto nan_actions = torch::zeros({20, 2});
  nan_actions[3][1] = NAN;
  save_safetensors(ep_dir / "data.safetensors", {{"action", nan_actions}, {"state", torch::zeros({20, 2})}});
  message = store.check_episode(1);
  EXPECT_NE(message.find("NaN"), std::string::npos) << message;

  // Corrupt video.
  save_safetensors(ep_dir / "data.safetensors",
                   {{"action", torch::zeros({20, 2})}, {"state", torch::zeros({20, 2})}});
  std::ofstream(ep_dir / "video.mp4", std::ios::binary) << "this is not a video";
  message = store.check_episode(1);
  EXPECT_NE(message.find("000001"), std::string::npos) << message;

  // Missing files.
  std::filesystem::remove_all(ep_dir);
  message = store.check_episode(1);
  EXPECT_NE(message.find("000001"), std::string::npos) << message;
  EXPECT_EQ(store.check_episode(0), "");
}

TEST(EpisodeStore, WriteRejectsMisalignedArrays) {
  test::TempDir tmp;
  EpisodeData ep;
  ep.frames = moving_frames(10);
  ep.actions = torch::zeros({9, 2});
  EXPECT_THROW(write_episode(tmp / "e", ep, 10), Error);
  EXPECT_FALSE(std::filesystem::exists(tmp / "e"));
}

}  // namespace dojo::data
