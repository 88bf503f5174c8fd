#include "data/clip_loader.h"

#include <torch/torch.h>

#include <fstream>

#include "core/error.h"
#include "test_util.h"

namespace dojo::data {
namespace {

torch::Tensor frames_with_index(int64_t t, int64_t h = 32, int64_t w = 32) {
  // Each frame is a flat grey level encoding its index (robust to H.264).
  return (torch::arange(t) * 8 + 16)
      .clamp_max(255)
      .to(torch::kUInt8)
      .view({t, 1, 1, 1})
      .expand({t, h, w, 3})
      .contiguous();
}

// Robot dataset: action[t] = (t, 2t, 7); one human dataset without actions.
std::filesystem::path make_dataset(const std::filesystem::path& dir, Embodiment embodiment, int episodes,
                                   int64_t frames) {
  DatasetInfo info;
  info.name = dir.filename().string();
  info.embodiment = embodiment;
  info.fps = 10;
  info.height = info.width = 32;
  StatsAccumulator acc;
  for (int e = 0; e < episodes; ++e) {
    EpisodeData ep;
    ep.frames = frames_with_index(frames);
    if (embodiment == Embodiment::kRobot) {
      const auto t = torch::arange(frames).to(torch::kFloat32);
      ep.actions = torch::stack({t, 2 * t, torch::full({frames}, 7.f)}, 1);  // [T, 3]
      ep.states = ep.actions.clone();
      acc.add(ep.actions);
    }
    char id[16];
    std::snprintf(id, sizeof id, "%06d", e);
    write_episode(dir / "episodes" / id, ep, 10.0);
    info.episodes.push_back({id, frames, "train", ""});
  }
  if (embodiment == Embodiment::kRobot) {
    info.action_slot = "dojosim_robot";
    info.action_dim = info.state_dim = 3;
    info.action_stats = acc.finish();
    info.state_stats = acc.finish();
  }
  write_dataset_info(dir, info);
  return dir;
}

ClipConfig small_config() {
  ClipConfig config;
  config.height = 16;
  config.width = 16;
  return config;
}

}  // namespace

TEST(ClipLoader, RobotClipHandComputed) {
  test::TempDir tmp;
  make_dataset(tmp / "robot", Embodiment::kRobot, 1, 40);
  ClipDataset dataset(EpisodeStore::open(tmp / "robot"), small_config());
  const auto clip = dataset.read(0, make_window(2, 2, 13));  // steps 2, 4, ..., 28
  ASSERT_EQ(clip.video.sizes(), (std::vector<int64_t>{13, 16, 16, 3}));
  // Frame k of the clip is episode frame 4 + 2k: grey level 8 * (4 + 2k) + 16.
  for (int k = 0; k < 13; ++k)
    EXPECT_NEAR(clip.video[k].to(torch::kFloat32).mean().item<float>(), 8 * (4 + 2 * k) + 16, 2.0) << k;
  ASSERT_EQ(clip.actions.sizes(), (std::vector<int64_t>{12, 384}));
  EXPECT_TRUE(clip.has_actions);
  // Dim 0: min 0, max 39 -> a_n(t) = 2t/39 - 1. Row j: a_n(step 1+j) - a_n(baseline of its chunk).
  // Steps are 2 + 2i; baselines are steps 0, 4, 8 of the window -> 2, 10, 18.
  for (int j = 0; j < 12; ++j) {
    const double step = 2 + 2 * (1 + j);
    const double base = 2 + 2 * (4 * (j / 4));
    EXPECT_NEAR(clip.actions[j][169].item<float>(), 2 * (step - base) / 39.0, 1e-5) << j;
    EXPECT_NEAR(clip.actions[j][170].item<float>(), 2 * 2 * (step - base) / 78.0, 1e-5) << j;
    EXPECT_EQ(clip.actions[j][171].item<float>(), 0.f);  // constant dimension -> 0
  }
  EXPECT_EQ(clip.actions.slice(1, 0, 169).abs().sum().item<float>(), 0.f);
  EXPECT_EQ(clip.actions.slice(1, 172).abs().sum().item<float>(), 0.f);
}

TEST(ClipLoader, AbsoluteActionsAblationKeepsNormalisedValues) {
  test::TempDir tmp;
  make_dataset(tmp / "robot", Embodiment::kRobot, 1, 40);
  auto config = small_config();
  config.relative_actions = false;
  ClipDataset dataset(EpisodeStore::open(tmp / "robot"), config);
  const auto clip = dataset.read(0, make_window(2, 2, 13));
  // Row j is the normalised action at step 1 + j of the window: episode step 2 + 2 (1 + j).
  for (int j = 0; j < 12; ++j) {
    const double step = 2 + 2 * (1 + j);
    EXPECT_NEAR(clip.actions[j][169].item<float>(), 2 * step / 39.0 - 1, 1e-5) << j;
  }
}

TEST(ClipLoader, SingleFrameClipsForImageTraining) {
  test::TempDir tmp;
  make_dataset(tmp / "robot", Embodiment::kRobot, 1, 40);
  auto config = small_config();
  config.num_frames = 1;
  ClipDataset dataset(EpisodeStore::open(tmp / "robot"), config);
  const auto clip = dataset.read(0, make_window(6, 1, 1));  // frame 7
  ASSERT_EQ(clip.video.sizes(), (std::vector<int64_t>{1, 16, 16, 3}));
  EXPECT_NEAR(clip.video.to(torch::kFloat32).mean().item<float>(), 8 * 7 + 16, 2.0);
  EXPECT_EQ(clip.actions.sizes(), (std::vector<int64_t>{0, 384}));
  std::mt19937_64 rng(1);
  EXPECT_EQ(dataset.sample(rng).video.size(0), 1);
}

TEST(ClipLoader, HumanClipCarriesLatentMask) {
  test::TempDir tmp;
  make_dataset(tmp / "human", Embodiment::kHuman, 1, 20);
  ClipDataset dataset(EpisodeStore::open(tmp / "human"), small_config());
  std::mt19937_64 rng(0);
  const auto clip = dataset.sample(rng);
  EXPECT_FALSE(clip.has_actions);
  EXPECT_EQ(clip.actions.slice(1, 352).sum().item<float>(), 12.f * 32.f);
  EXPECT_EQ(clip.actions.slice(1, 0, 352).abs().sum().item<float>(), 0.f);
}

TEST(ClipLoader, MixtureFollowsWeights) {
  test::TempDir tmp;
  make_dataset(tmp / "robot", Embodiment::kRobot, 1, 20);
  make_dataset(tmp / "human", Embodiment::kHuman, 1, 20);
  ClipMixture mixture;
  mixture.add(std::make_shared<ClipDataset>(EpisodeStore::open(tmp / "robot"), small_config()), 1.0);
  mixture.add(std::make_shared<ClipDataset>(EpisodeStore::open(tmp / "human"), small_config()), 3.0);
  EXPECT_DOUBLE_EQ(mixture.probabilities()[1], 0.75);
  std::mt19937_64 rng(3);
  int robot = 0;
  constexpr int kDraws = 200;
  for (int i = 0; i < kDraws; ++i) robot += mixture.sample(rng).has_actions ? 1 : 0;
  // Binomial(200, 0.25): mean 50, sd ~6.1.
  EXPECT_GT(robot, 30);
  EXPECT_LT(robot, 70);
}

TEST(ClipLoader, PrefetchStreamIndependentOfWorkerCount) {
  test::TempDir tmp;
  make_dataset(tmp / "robot", Embodiment::kRobot, 3, 30);
  auto mixture = std::make_shared<ClipMixture>();
  mixture->add(std::make_shared<ClipDataset>(EpisodeStore::open(tmp / "robot"), small_config()), 1.0);
  std::vector<Batch> one, two;
  {
    PrefetchLoader loader(mixture, {2, 1, 2, 11});
    for (int i = 0; i < 4; ++i) one.push_back(loader.next());
  }
  {
    PrefetchLoader loader(mixture, {2, 3, 2, 11});
    for (int i = 0; i < 4; ++i) two.push_back(loader.next());
  }
  for (int i = 0; i < 4; ++i) {
    EXPECT_EQ(one[i].index, i);
    EXPECT_TRUE(torch::equal(one[i].video, two[i].video)) << i;
    EXPECT_TRUE(torch::equal(one[i].actions, two[i].actions)) << i;
  }
  ASSERT_EQ(one[0].video.sizes(), (std::vector<int64_t>{2, 13, 16, 16, 3}));
}

TEST(ClipLoader, BadEpisodeFailsOrIsSkippedAndCounted) {
  test::TempDir tmp;
  make_dataset(tmp / "robot", Embodiment::kRobot, 2, 30);
  std::ofstream(tmp / "robot" / "episodes" / "000001" / "video.mp4", std::ios::binary) << "garbage";
  {
    ClipDataset strict(EpisodeStore::open(tmp / "robot"), small_config());
    std::mt19937_64 rng(0);
    bool threw = false;
    for (int i = 0; i < 40 && !threw; ++i) {
      try {
        (void)strict.sample(rng);
      } catch (const Error& e) {
        threw = true;
        EXPECT_NE(std::string(e.what()).find("000001"), std::string::npos) << e.what();
      }
    }
    EXPECT_TRUE(threw);
  }
  ClipDataset lenient(EpisodeStore::open(tmp / "robot"), small_config(), "train", /*skip_bad=*/true);
  std::mt19937_64 rng(0);
  for (int i = 0; i < 40; ++i) EXPECT_EQ(lenient.sample(rng).episode, 0u);
  EXPECT_EQ(lenient.skipped_episodes(), 1);
}

TEST(ClipLoader, WorkerErrorReachesConsumer) {
  test::TempDir tmp;
  make_dataset(tmp / "robot", Embodiment::kRobot, 1, 30);
  std::ofstream(tmp / "robot" / "episodes" / "000000" / "video.mp4", std::ios::binary) << "garbage";
  auto mixture = std::make_shared<ClipMixture>();
  mixture->add(std::make_shared<ClipDataset>(EpisodeStore::open(tmp / "robot"), small_config()), 1.0);
  PrefetchLoader loader(mixture, {2, 2, 2, 0});
  EXPECT_THROW(loader.next(), Error);
}

// A 40 x 80 frame centre-cropped to a square loses 20 columns each side: a keypoint at the frame's
// centre stays at the centre, one at u = 0.2 (16 px) falls off the crop.
TEST(ClipLoader, KeypointsFollowTheCropAndResize) {
  auto kp = torch::tensor({0.5f, 0.5f, 1.f, 0.2f, 0.5f, 1.f, 0.75f, 0.25f, 1.f}).view({1, 3, 3});
  const auto out = crop_keypoints(kp, 40, 80, 16, 16);
  EXPECT_NEAR(out[0][0][0].item<float>(), 0.5f, 1e-6);
  EXPECT_NEAR(out[0][0][1].item<float>(), 0.5f, 1e-6);
  EXPECT_EQ(out[0][1][2].item<float>(), 0.f);                       // cropped away
  EXPECT_NEAR(out[0][2][0].item<float>(), (60 - 20) / 40.f, 1e-6);  // 60 px in the frame, 40 in the crop
  EXPECT_NEAR(out[0][2][1].item<float>(), 0.25f, 1e-6);
  EXPECT_EQ(out[0][2][2].item<float>(), 1.f);
}

// A model's own ranges replace the dataset's: the same motion gives the same numbers whichever
// dataset it comes from. Dim 0 spans [0, 39] in the data; with [0, 78] its deltas halve.
TEST(ClipLoader, GivenActionStatsReplaceTheDatasets) {
  test::TempDir tmp;
  make_dataset(tmp / "robot", Embodiment::kRobot, 1, 40);
  auto config = small_config();
  ArrayStats wide;
  wide.min = {0.f, 0.f, 0.f};
  wide.max = {78.f, 78.f, 14.f};
  config.action_stats = wide;
  ClipDataset dataset(EpisodeStore::open(tmp / "robot"), config);
  const auto clip = dataset.read(0, make_window(2, 2, 13));
  for (int j = 0; j < 12; ++j) {
    const double step = 2 + 2 * (1 + j);
    const double base = 2 + 2 * (4 * (j / 4));
    EXPECT_NEAR(clip.actions[j][169].item<float>(), 2 * (step - base) / 78.0, 1e-5) << j;
  }
  wide.min.pop_back();
  wide.max.pop_back();
  config.action_stats = wide;
  EXPECT_THROW(ClipDataset(EpisodeStore::open(tmp / "robot"), config), Error);
}

// Episodes kept decoded give the clips that decoding each clip gives, bit for bit (frames with
// texture, resized from 32 to 24 x 16 so that the resize matters), within the budget; an episode
// that does not fit is read per clip, and a damaged one is read per clip and still fails naming it.
TEST(ClipLoader, DecodedEpisodesGiveTheSameClipsWithinTheirBudget) {
  test::TempDir tmp;
  make_dataset(tmp / "robot", Embodiment::kRobot, 3, 40);
  for (int e = 0; e < 3; ++e) {  // replace the flat grey frames with textured ones
    char id[16];
    std::snprintf(id, sizeof id, "%06d", e);
    const auto dir = tmp / "robot" / "episodes" / id;
    auto ep = EpisodeStore::open(tmp / "robot").load(static_cast<size_t>(e));
    const auto yx = torch::arange(32).view({1, 32, 1, 1}) * 5 + torch::arange(32).view({1, 1, 32, 1}) * 3;
    ep.frames =
        (yx + torch::arange(40).view({40, 1, 1, 1}) * (7 + e) + torch::arange(3).view({1, 1, 1, 3}) * 60)
            .remainder(256)
            .to(torch::kUInt8);  // [40, 32, 32, 3]
    write_episode(dir, ep, 10.0);
  }
  auto config = small_config();
  config.height = 24;
  config.width = 16;
  auto uncached_config = config;
  EXPECT_EQ(uncached_config.decoded_cache_mib, 0);  // off unless a trainer asks
  config.decoded_cache_mib = 512;
  ClipDataset cached(EpisodeStore::open(tmp / "robot"), config);
  ClipDataset uncached(EpisodeStore::open(tmp / "robot"), uncached_config);
  std::mt19937_64 a(5), b(5);
  for (int i = 0; i < 30; ++i) {
    const auto x = cached.sample(a), y = uncached.sample(b);
    ASSERT_EQ(x.episode, y.episode);
    EXPECT_TRUE(torch::equal(x.video, y.video)) << i;
    EXPECT_TRUE(torch::equal(x.actions, y.actions)) << i;
  }
  EXPECT_EQ(cached.decoded_cache_bytes(), 3 * 40 * 24 * 16 * 3);
  EXPECT_EQ(uncached.decoded_cache_bytes(), 0);

  // At 512 x 512 an episode is 30 MiB: a budget of 1 MiB keeps none, and every clip still reads.
  config.height = config.width = 512;
  config.decoded_cache_mib = 1;
  ClipDataset over(EpisodeStore::open(tmp / "robot"), config);
  std::mt19937_64 c(1);
  for (int i = 0; i < 3; ++i) EXPECT_EQ(over.sample(c).video.size(1), 512);
  EXPECT_EQ(over.decoded_cache_bytes(), 0);

  // At 256 x 256 an episode is 7.5 MiB: 16 MiB keeps two of the three, drawn by one thread or by
  // two workers at once, and the clips stay those of a fresh decode.
  const int64_t episode_bytes = 40 * 256 * 256 * 3;
  config.height = config.width = uncached_config.height = uncached_config.width = 256;
  config.decoded_cache_mib = 16;
  ClipDataset partial(EpisodeStore::open(tmp / "robot"), config);
  ClipDataset partial_reference(EpisodeStore::open(tmp / "robot"), uncached_config);
  std::mt19937_64 d(9), e(9);
  for (int i = 0; i < 30; ++i)
    EXPECT_TRUE(torch::equal(partial.sample(d).video, partial_reference.sample(e).video));
  EXPECT_EQ(partial.decoded_cache_bytes(), 2 * episode_bytes);
  auto threaded = std::make_shared<ClipMixture>(), reference = std::make_shared<ClipMixture>();
  auto threaded_dataset = std::make_shared<ClipDataset>(EpisodeStore::open(tmp / "robot"), config);
  threaded->add(threaded_dataset, 1.0);
  reference->add(std::make_shared<ClipDataset>(EpisodeStore::open(tmp / "robot"), uncached_config), 1.0);
  PrefetchLoader two(threaded, {4, 2, 4, 3}), one(reference, {4, 1, 4, 3});
  for (int i = 0; i < 6; ++i) EXPECT_TRUE(torch::equal(two.next().video, one.next().video)) << "batch " << i;
  EXPECT_GT(threaded_dataset->decoded_cache_bytes(), 0);
  EXPECT_LE(threaded_dataset->decoded_cache_bytes(), 2 * episode_bytes);

  std::ofstream(tmp / "robot" / "episodes" / "000001" / "video.mp4", std::ios::binary) << "garbage";
  auto damaged_config = small_config();
  damaged_config.decoded_cache_mib = 1;
  ClipDataset damaged(EpisodeStore::open(tmp / "robot"), damaged_config);
  (void)damaged.read(0, make_window(0, 1, 13));
  try {
    (void)damaged.read(1, make_window(0, 1, 13));
    ADD_FAILURE() << "a damaged episode read";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("000001"), std::string::npos) << e.what();
  }
  EXPECT_EQ(damaged.decoded_cache_bytes(), 40 * 16 * 16 * 3);
}

}  // namespace dojo::data
