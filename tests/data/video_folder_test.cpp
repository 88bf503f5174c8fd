// Video folders: recursive discovery, sidecar text, DreamDojo's skip rule, a real camera clip
// (opencv-doc), and errors naming the file.
#include "data/video_folder.h"

#include <torch/torch.h>

#include <fstream>

#include "core/error.h"
#include "data/clip_loader.h"
#include "io/video.h"
#include "test_util.h"

namespace fs = std::filesystem;

namespace dojo::data {
namespace {

void make_video(const fs::path& path, int64_t frames, int first_level = 10) {
  fs::create_directories(path.parent_path());
  auto levels = (torch::arange(frames) * 4 + first_level).to(torch::kUInt8);
  io::VideoWriterOptions options;
  options.fps = 15;
  options.crf = 10;
  io::write_video(path.string(), levels.view({frames, 1, 1, 1}).expand({frames, 24, 32, 3}).contiguous(),
                  options);
}

}  // namespace

TEST(VideoFolder, SkipRule) {
  EXPECT_TRUE(dreamdojo_skips("clips/cam_left.mp4"));
  EXPECT_TRUE(dreamdojo_skips("clips/x_resize.mp4"));
  EXPECT_TRUE(dreamdojo_skips("clips/pad_3.mp4"));
  EXPECT_FALSE(dreamdojo_skips("left/clip.mp4"));  // only the file name counts
  EXPECT_TRUE(dreamdojo_skips("xdof/a/clip_640_480.mp4"));
  EXPECT_FALSE(dreamdojo_skips("xdof/a/clip_320_240.mp4"));
}

TEST(VideoFolder, FindsVideosRecursivelyWithSidecarText) {
  test::TempDir tmp;
  const fs::path root = tmp / "hv";
  make_video(root / "a" / "one.mp4", 20);
  std::ofstream(root / "a" / "one.txt") << "stack the blocks\n";
  make_video(root / "b" / "c" / "two.MP4", 15, 50);
  make_video(root / "b" / "left_cam.mp4", 14);
  std::ofstream(root / "notes.md") << "not a video";
  const auto real = test::sample_video("vtest.avi");
  if (!real.empty()) {
    fs::create_directories(root / "real");
    fs::copy_file(real, root / "real" / "vtest.avi");
  }

  const auto source = open_dataset(root);
  EXPECT_EQ(source->format(), "video-folder");
  const auto& info = source->info();
  ASSERT_EQ(info.episodes.size(), real.empty() ? 3u : 4u);
  EXPECT_EQ(info.episodes[0].id, "a/one.mp4");
  EXPECT_EQ(info.episodes[0].task, "stack the blocks");
  EXPECT_EQ(info.episodes[0].frames, 20);
  EXPECT_EQ(info.episodes[1].id, "b/c/two.MP4");
  EXPECT_EQ(info.embodiment, Embodiment::kHuman);
  EXPECT_EQ(info.width, 32);
  const auto frames = source->read_frames(1, {0, 14});
  EXPECT_NEAR(frames[1].to(torch::kFloat32).mean().item<float>(), 50 + 4 * 14, 1.5);
  EXPECT_EQ(source->read_arrays(0).meta.at("task"), "stack the blocks");

  OpenOptions skip;
  skip.skip_dreamdojo_names = true;
  const auto skipped = open_dataset(root, skip);
  EXPECT_EQ(skipped->size(), info.episodes.size() - 1);
  EXPECT_EQ(dynamic_cast<const VideoFolderDataset&>(*skipped).skipped(), 1);
}

TEST(VideoFolder, ClipsFromARealCameraClip) {
  const auto real = test::sample_video("vtest.avi");
  if (real.empty()) GTEST_SKIP() << "opencv-doc not installed";
  test::TempDir tmp;
  fs::create_directories(tmp / "real");
  fs::copy_file(real, tmp / "real" / "vtest.avi");
  ClipConfig config;
  config.height = 24;
  config.width = 32;
  ClipDataset dataset(open_dataset(tmp / "real"), config, "all");
  EXPECT_GT(dataset.source().info().episodes[0].frames, 100);
  std::mt19937_64 rng(7);
  const auto clip = dataset.sample(rng);
  EXPECT_EQ(clip.video.sizes(), (std::vector<int64_t>{13, 24, 32, 3}));
  EXPECT_FALSE(clip.has_actions);
  EXPECT_GT(clip.video.to(torch::kFloat32).std().item<float>(), 5.f);  // real content, not blank
}

TEST(VideoFolder, BadInputsNameThePath) {
  test::TempDir tmp;
  make_video(tmp / "hv" / "good.mp4", 10);
  std::ofstream(tmp / "hv" / "broken.mp4") << "definitely not an mp4";
  const std::string message = test::error_message([&] { VideoFolderDataset::open(tmp / "hv"); });
  EXPECT_NE(message.find((tmp / "hv" / "broken.mp4").string()), std::string::npos) << message;
  fs::create_directories(tmp / "empty");
  EXPECT_EQ(test::error_message([&] { open_dataset(tmp / "empty"); }),
            (tmp / "empty").string() +
                ": cannot tell the dataset format (no info.json, no meta/info.json, no *.hdf5 beside *.mp4, "
                "no video files)");
  EXPECT_EQ(test::error_message([&] { open_dataset(tmp / "nope"); }),
            (tmp / "nope").string() + ": no such dataset directory");
}

TEST(VideoFolder, DataInfoJsonAndConvert) {
  test::TempDir tmp;
  make_video(tmp / "hv" / "one.mp4", 16);
  std::ofstream(tmp / "hv" / "one.txt") << "wave";
  auto r = test::run_dojo("data info " + (tmp / "hv").string() + " --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto j = nlohmann::json::parse(r.output);
  EXPECT_EQ(j.at("format"), "video-folder");
  EXPECT_EQ(j.at("frames"), 16);
  EXPECT_EQ(j.at("tasks"), nlohmann::json({"wave"}));
  r = test::run_dojo("data convert " + (tmp / "hv").string() + " " + (tmp / "out").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto store = EpisodeStore::open(tmp / "out");
  EXPECT_EQ(store.info().embodiment, Embodiment::kHuman);
  EXPECT_EQ(store.info().episodes[0].task, "wave");
  EXPECT_EQ(store.load(0).frames.size(0), 16);
  r = test::run_dojo("data stats " + (tmp / "hv").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("action-free"), std::string::npos) << r.output;
}

}  // namespace dojo::data
