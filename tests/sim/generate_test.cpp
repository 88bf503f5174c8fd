#include "sim/generate.h"

#include <torch/torch.h>

#include "core/error.h"
#include "data/episode_source.h"
#include "data/episode_store.h"
#include "test_util.h"

namespace dojo::sim {
namespace {

GenerateOptions small(const std::string& embodiment, int episodes) {
  GenerateOptions o;
  o.embodiment = embodiment;
  o.episodes = episodes;
  o.frames = 16;
  o.width = o.height = 32;
  o.seed = 5;
  o.workers = 2;
  return o;
}

// Every file of a dataset, by relative path.
std::map<std::string, std::string> snapshot(const std::filesystem::path& dir) {
  std::map<std::string, std::string> files;
  for (const auto& e : std::filesystem::recursive_directory_iterator(dir))
    if (e.is_regular_file())
      files[std::filesystem::relative(e.path(), dir).string()] = test::read_file(e.path());
  return files;
}

}  // namespace

TEST(Generate, SameSeedSameBytesWhateverTheWorkers) {
  test::TempDir tmp;
  auto a = small("robot", 3);
  auto b = a;
  b.workers = 1;
  generate_dataset(tmp / "a", a);
  generate_dataset(tmp / "b", b);
  const auto sa = snapshot(tmp / "a"), sb = snapshot(tmp / "b");
  ASSERT_EQ(sa.size(), sb.size());
  for (const auto& [name, bytes] : sa) {
    if (name == "info.json") continue;  // holds the dataset's directory name
    ASSERT_TRUE(sb.count(name)) << name;
    EXPECT_TRUE(bytes == sb.at(name)) << name << " differs";
  }
  auto c = a;
  c.seed = 6;
  generate_dataset(tmp / "c", c);
  EXPECT_NE(snapshot(tmp / "c").at("episodes/000000/video.mp4"), sa.at("episodes/000000/video.mp4"));
}

TEST(Generate, InterruptedRunResumes) {
  test::TempDir tmp;
  const auto o = small("human", 3);
  generate_dataset(tmp / "d", o);
  const auto before = snapshot(tmp / "d");
  // Simulate a run killed mid-way: one episode missing, one half-written temp dir.
  std::filesystem::remove_all(tmp / "d" / "episodes" / "000001");
  std::filesystem::create_directories(tmp / "d" / "episodes" / "000001.tmp-999");
  std::filesystem::remove(tmp / "d" / "info.json");
  const auto summary = generate_dataset(tmp / "d", o);
  EXPECT_EQ(summary.generated, 1);
  EXPECT_EQ(summary.reused, 2);
  EXPECT_FALSE(std::filesystem::exists(tmp / "d" / "episodes" / "000001.tmp-999"));
  EXPECT_EQ(snapshot(tmp / "d"), before);
}

TEST(Generate, RawFramesAreTheMp4RunsPicturesAndResume) {
  test::TempDir tmp;
  auto o = small("robot", 2);
  generate_dataset(tmp / "mp4", o);
  o.video_format = data::VideoFormat::kRaw;
  generate_dataset(tmp / "raw", o);
  const auto mp4 = data::EpisodeStore::open(tmp / "mp4"), raw = data::EpisodeStore::open(tmp / "raw");
  EXPECT_EQ(raw.info().video_format, data::VideoFormat::kRaw);
  EXPECT_EQ(raw.info().generator.at("video_format"), "raw");
  // The same renders, stored exactly: within H.264's loss of the mp4's decode.
  const auto a = mp4.load(1).frames.to(torch::kFloat32), b = raw.load(1).frames.to(torch::kFloat32);
  ASSERT_EQ(a.sizes(), b.sizes());
  EXPECT_LT((a - b).abs().mean().item<double>(), 3.0);
  EXPECT_TRUE(torch::equal(mp4.load(1).actions, raw.load(1).actions));
  // A raw episode counts as finished when resuming.
  std::filesystem::remove_all(tmp / "raw" / "episodes" / "000000");
  const auto summary = generate_dataset(tmp / "raw", o);
  EXPECT_EQ(summary.generated, 1);
  EXPECT_EQ(summary.reused, 1);
}

TEST(Generate, RefusesDirectoryOfAnotherRun) {
  test::TempDir tmp;
  auto o = small("human", 1);
  generate_dataset(tmp / "d", o);
  o.seed = 99;
  const auto message = test::error_message([&] { generate_dataset(tmp / "d", o); });
  EXPECT_NE(message.find("seed"), std::string::npos) << message;
}

TEST(Generate, RobotDatasetInfoAndSplits) {
  test::TempDir tmp;
  auto o = small("robot", 8);
  o.val_fraction = 0.25;
  generate_dataset(tmp / "r", o);
  const auto store = data::EpisodeStore::open(tmp / "r");
  const auto& info = store.info();
  EXPECT_EQ(info.embodiment, data::Embodiment::kRobot);
  EXPECT_EQ(info.action_slot, "dojosim_robot");
  EXPECT_GT(info.action_dim, 0);
  EXPECT_EQ(info.split_counts().at("val"), 2);
  EXPECT_EQ(info.split_counts().at("train"), 6);
  ASSERT_TRUE(info.action_stats.has_value());
  for (int d = 0; d < info.action_dim; ++d) EXPECT_LE(info.action_stats->min[d], info.action_stats->max[d]);
  for (size_t i = 0; i < store.size(); ++i) EXPECT_EQ(store.check_episode(i), "") << i;
}

// --cameras side: every episode records the fixed side view beside the ego one, the same frames
// counted, a different picture; tiled side by side it is the multi-view canvas.
TEST(Generate, ASecondCameraIsRecordedAndTiles) {
  test::TempDir tmp;
  auto o = small("robot", 2);
  o.cameras = {"side"};
  generate_dataset(tmp / "r", o);
  const auto store = data::EpisodeStore::open(tmp / "r");
  EXPECT_EQ(store.info().cameras, (std::vector<std::string>{"ego", "side"}));
  EXPECT_TRUE(std::filesystem::exists(store.episode_dir(0) / "side.mp4"));
  const auto ego = data::open_dataset(tmp / "r");
  data::OpenOptions side_only;
  side_only.camera = "side";
  const auto side = data::open_dataset(tmp / "r", side_only);
  const auto a = ego->read_frames(0, {0, 5}), b = side->read_frames(0, {0, 5});
  EXPECT_EQ(a.sizes(), b.sizes());
  EXPECT_GT((a.to(torch::kFloat) - b.to(torch::kFloat)).abs().mean().item<double>(), 10.0)
      << "another viewpoint, another picture";
  data::OpenOptions both;
  both.views = {"ego", "side"};
  const auto tiled = data::open_dataset(tmp / "r", both);
  EXPECT_EQ(tiled->info().width, 2 * ego->info().width);
  const auto canvas = tiled->read_frames(0, {0, 5});
  EXPECT_TRUE(torch::equal(canvas.narrow(2, 0, a.size(2)), a));
  EXPECT_TRUE(torch::equal(canvas.narrow(2, a.size(2), a.size(2)), b));
  side_only.camera = "wrist";
  EXPECT_NE(test::error_message([&] {
              data::open_dataset(tmp / "r", side_only);
            }).find("no camera 'wrist' (cameras: ego, side)"),
            std::string::npos);
}

TEST(Generate, EvaluationSplits) {
  test::TempDir tmp;
  for (const std::string split : {"ood-objects", "counterfactual", "novel-background"}) {
    auto o = small("robot", 2);
    o.split = split;
    generate_dataset(tmp / split, o);
    const auto store = data::EpisodeStore::open(tmp / split);
    const auto meta = store.load_arrays(0).meta;
    if (split == "ood-objects") {
      EXPECT_TRUE(meta["ood_objects"].get<bool>());
    }
    if (split == "novel-background") {
      EXPECT_TRUE(meta["novel_background"].get<bool>());
    }
    EXPECT_EQ(store.info().episodes[0].split, split);
  }
  auto bad = small("human", 1);
  bad.split = "ood-objects";
  EXPECT_THROW(generate_dataset(tmp / "bad", bad), Error);
}

TEST(Generate, PlayBehaviorsTakeTurns) {
  test::TempDir tmp;
  auto o = small("robot", 4);
  o.val_fraction = 0;
  o.play_fraction = 1;
  o.play_behaviors = {"teleop_play", "random_motion"};
  generate_dataset(tmp / "p", o);
  const auto store = data::EpisodeStore::open(tmp / "p");
  for (size_t i = 0; i < store.size(); ++i)
    EXPECT_EQ(store.load_arrays(i).meta.at("controller").at("behavior"),
              i % 2 ? "random_motion" : "teleop_play")
        << "episode " << i;
  o.play_behaviors = {"teleop_play"};  // the kinds are part of the run's identity
  const auto message = test::error_message([&] { generate_dataset(tmp / "p", o); });
  EXPECT_NE(message.find("play_behaviors"), std::string::npos) << message;
  o.play_behaviors = {"bin_pick"};
  EXPECT_NE(test::error_message([&] { generate_dataset(tmp / "q", o); }).find("'bin_pick' is not play"),
            std::string::npos);
}

TEST(Generate, PolicySetTakesTurnsAndIdleHoldsStill) {
  test::TempDir tmp;
  auto o = small("robot", 6);
  o.val_fraction = 0;
  GenerateOptions::NamedPolicy idle{"idle", {}}, slow{"slow", {}};
  idle.options.behavior = RobotBehavior::kIdle;
  slow.options.quality.speed = 0.6;
  o.policies = {idle, slow};
  generate_dataset(tmp / "p", o);
  const auto store = data::EpisodeStore::open(tmp / "p");
  std::map<std::string, int> drawn;
  for (size_t i = 0; i < store.size(); ++i) {
    const auto episode = store.load_arrays(i);
    const auto name = episode.meta.at("policy").get<std::string>();
    ++drawn[name];
    const auto moved = (episode.actions - episode.actions[0]).abs().max().item<float>();  // [T, 6] vs row 0
    if (name == "idle") {
      EXPECT_EQ(moved, 0.0f) << "episode " << i << ": an idle policy's commands change";
      EXPECT_EQ(episode.meta.at("success").get<double>(), 0.0) << "episode " << i;
    } else {
      EXPECT_GT(moved, 0.1f) << "episode " << i << ": the slow bin policy never moves";
    }
  }
  EXPECT_EQ(drawn, (std::map<std::string, int>{{"idle", 3}, {"slow", 3}}))
      << "the policies do not take turns";
  // The set is part of the run's identity: another set in the same directory is refused.
  o.policies = {idle};
  const auto message = test::error_message([&] { generate_dataset(tmp / "p", o); });
  EXPECT_NE(message.find("policies"), std::string::npos) << message;
  o.policies.clear();  // and so is the expert/good/medium mix
  const auto without = test::error_message([&] { generate_dataset(tmp / "p", o); });
  EXPECT_NE(without.find("policies"), std::string::npos) << without;
  // A set and a quality preset both choose the policy; human data runs no robot policy.
  auto both = small("robot", 1);
  both.policies = {idle};
  both.quality = "poor";
  EXPECT_NE(test::error_message([&] { generate_dataset(tmp / "both", both); }).find("--quality"),
            std::string::npos);
  auto human = small("human", 1);
  human.policies = {idle};
  EXPECT_NE(test::error_message([&] { generate_dataset(tmp / "human", human); }).find("robot train split"),
            std::string::npos);
}

}  // namespace dojo::sim
