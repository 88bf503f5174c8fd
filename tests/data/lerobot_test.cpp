// LeRobot v2.1 / v3.0 readers on datasets the tests build themselves (parquet from our writer,
// mp4 from our VideoWriter), GR-1 slot mapping, clear errors for malformed data, and the
// `dojo data info/convert/stats` commands.
#include "data/lerobot.h"

#include <torch/torch.h>

#include <cstdlib>
#include <fstream>

#include "core/error.h"
#include "data/clip_loader.h"
#include "io/parquet_writer.h"
#include "io/video.h"
#include "lerobot_writer.h"
#include "test_util.h"

namespace fs = std::filesystem;

namespace dojo::data {
namespace {

using namespace lerobot_fixture;

void expect_gr1_mapping(const LeRobotDataset& ds, size_t episode) {
  const auto arrays = ds.read_arrays(episode);
  ASSERT_EQ(arrays.actions.sizes(), (std::vector<int64_t>{30, 29}));
  ASSERT_EQ(arrays.states.sizes(), (std::vector<int64_t>{30, kRawDim}));
  const int e = static_cast<int>(episode);
  for (int64_t k : {0, 17, 29}) {
    // Slot order: left_arm (raw 0:7), right_arm (22:29), left_hand (7:13), right_hand (29:35), waist (41:44).
    EXPECT_FLOAT_EQ(arrays.actions[k][0].item<float>(), raw_action(e, k, 0));
    EXPECT_FLOAT_EQ(arrays.actions[k][7].item<float>(), raw_action(e, k, 22));
    EXPECT_FLOAT_EQ(arrays.actions[k][14].item<float>(), raw_action(e, k, 7));
    EXPECT_FLOAT_EQ(arrays.actions[k][20].item<float>(), raw_action(e, k, 29));
    EXPECT_FLOAT_EQ(arrays.actions[k][28].item<float>(), raw_action(e, k, 43));
    EXPECT_FLOAT_EQ(arrays.states[k][5].item<float>(), raw_action(e, k, 5) - 1);
  }
}

}  // namespace

TEST(LeRobot, PathTemplatesAndRobotDetection) {
  EXPECT_EQ(format_path_template("data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet", {},
                                 {{"episode_chunk", 1}, {"episode_index", 1042}}, "info.json"),
            "data/chunk-001/episode_001042.parquet");
  EXPECT_EQ(format_path_template("videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
                                 {{"video_key", "observation.images.top"}},
                                 {{"chunk_index", 0}, {"file_index", 12}}, "x"),
            "videos/observation.images.top/chunk-000/file-012.mp4");
  EXPECT_EQ(test::error_message([] { format_path_template("{nope}", {}, {}, "info.json"); }),
            "info.json: unknown field '{nope}' in path template '{nope}'");
  EXPECT_EQ(detect_robot("fourier_gr1_arms_waist"), "gr1");
  EXPECT_EQ(detect_robot("unitree_g1"), "g1");
  EXPECT_EQ(detect_robot("bimanual_yam"), "yam");
  EXPECT_EQ(detect_robot("AgiBot"), "agibot");
  EXPECT_EQ(detect_robot("so100"), "");
  // Each released layout fills exactly its slot, with keys its default modality defines.
  for (const auto& layout : robot_layouts()) {
    int width = 0;
    for (const auto& [key, w] : layout.action_order) {
      width += w;
      const ModalityRange* r = layout.default_modality.find_action(key);
      ASSERT_NE(r, nullptr) << layout.name << " " << key;
      EXPECT_EQ(r->width(), w) << layout.name << " " << key;
    }
    EXPECT_EQ(width, layout.slot.width()) << layout.name;
  }
}

// The robot comes from --embodiment or info.json's robot_type, never from the path: a GR-1 set
// under a path that says "gr1" but with a robot_type naming no known robot has no action slot
// until the robot is named.
TEST(LeRobot, TheRobotIsNamedNeverReadFromThePath) {
  test::TempDir tmp;
  Fixture fx;
  fx.robot_type = "";
  const auto root = make_lerobot(tmp / "PhysicalAI-Robotics-GR00T-Teleop-GR1" / "gr1_unlabelled", fx);
  EXPECT_EQ(open_dataset(root)->info().action_slot, "");
  OpenOptions named;
  named.embodiment = "gr1";
  EXPECT_EQ(open_dataset(root, named)->info().action_slot, "gr1");
  EXPECT_EQ(open_dataset(root, named)->info().action_dim, 29);
}

// Without meta/modality.json a known robot falls back to its released layout: a G1 dataset's
// 43-d actions land in the G1 slot [58, 101).
TEST(LeRobot, G1WithoutModalityUsesTheReleasedLayout) {
  test::TempDir tmp;
  Fixture fx;
  fx.raw_dim = 43;
  fx.robot_type = "unitree_g1";
  fx.modality = false;
  fx.frames = 14;
  ClipConfig config;
  config.height = config.width = 16;
  config.strides = {1};
  const auto source = open_dataset(make_lerobot(tmp / "robot", fx));
  EXPECT_EQ(source->info().action_slot, "g1");
  EXPECT_EQ(source->info().action_dim, 43);
  ClipDataset dataset(source, config);
  const auto clip = dataset.read(0, make_window(0, 1, 13));
  EXPECT_EQ(clip.actions.slice(1, 0, 58).abs().sum().item<float>(), 0.f);
  EXPECT_EQ(clip.actions.slice(1, 101).abs().sum().item<float>(), 0.f);
  // G1 keeps its stored order: slot column 58 + d is raw dim d; min 0.01 d, max 113 + 0.01 d.
  for (int j = 0; j < 12; ++j) {
    const double step = 1 + j, base = 4 * (j / 4);
    EXPECT_NEAR(clip.actions[j][58 + 42].item<float>(), 2 * (step - base) / 113.0, 1e-5) << j;
  }
  OpenOptions yam;
  yam.embodiment = "yam";  // 46 dims expected, the dataset has 43
  EXPECT_EQ(
      test::error_message([&] { LeRobotDataset::open(tmp / "robot", yam); }),
      (tmp / "robot").string() +
          ": built-in yam layout: action.joint_pos_action_right ends at 46 beyond the 43-d action feature");
}

TEST(LeRobot, V21ReadsEpisodesTasksStatsAndGr1Slot) {
  test::TempDir tmp;
  const auto ds = LeRobotDataset::open(make_lerobot(tmp / "gr1_v21"));
  EXPECT_EQ(ds->format(), "lerobot-v2.1");
  const auto& info = ds->info();
  ASSERT_EQ(info.episodes.size(), 2u);
  EXPECT_EQ(info.total_frames(), 60);
  EXPECT_EQ(info.action_slot, "gr1");
  EXPECT_EQ(info.action_dim, 29);
  EXPECT_EQ(info.state_dim, kRawDim);
  EXPECT_EQ(info.episodes[1].task, "wave");
  EXPECT_EQ(ds->tasks(), kTasks);
  EXPECT_EQ(ds->camera(), kCamera);
  ASSERT_TRUE(info.action_stats.has_value());
  EXPECT_FLOAT_EQ(info.action_stats->min[7], raw_action(0, 0, 22));  // stats sliced like the actions
  EXPECT_FLOAT_EQ(info.action_stats->max[7], raw_action(1, 29, 22));
  expect_gr1_mapping(*ds, 1);
  const auto frames = ds->read_frames(1, {0, 13, 29});  // [3, 32, 32, 3]
  ASSERT_EQ(frames.sizes(), (std::vector<int64_t>{3, 32, 32, 3}));
  EXPECT_NEAR(test::mean_level(frames[0]), level(30), 1.5);
  EXPECT_NEAR(test::mean_level(frames[1]), level(43), 1.5);
  EXPECT_NEAR(test::mean_level(frames[2]), level(59), 1.5);
}

TEST(LeRobot, V30ReadsSharedFilesAndLocatesFramesByTimestamp) {
  test::TempDir tmp;
  Fixture fx;
  fx.v3 = true;
  const auto ds = LeRobotDataset::open(make_lerobot(tmp / "gr1_v30", fx));
  EXPECT_EQ(ds->format(), "lerobot-v3.0");
  ASSERT_EQ(ds->info().episodes.size(), 2u);
  EXPECT_EQ(ds->info().episodes[0].task, "pick up the cup");
  EXPECT_EQ(ds->tasks(), kTasks);
  expect_gr1_mapping(*ds, 0);
  expect_gr1_mapping(*ds, 1);
  // Episode 1 starts 1.5 s into the shared video: its frame k is video frame 30 + k.
  const auto frames = ds->read_frames(1, {0, 29, 5});
  EXPECT_NEAR(test::mean_level(frames[0]), level(30), 1.5);
  EXPECT_NEAR(test::mean_level(frames[1]), level(59), 1.5);
  EXPECT_NEAR(test::mean_level(frames[2]), level(35), 1.5);
}

// v3.0's default codec is AV1 (LeRobot encodes with g=2, crf=30): re-encode the shared video
// with the ffmpeg CLI (libaom, which takes 32x32 frames) and locate frames by timestamp again.
TEST(LeRobot, V30Av1VideoIsReadByTimestamp) {
  if (std::system("ffmpeg -hide_banner -encoders 2>/dev/null | grep -q libaom-av1") != 0)
    GTEST_SKIP() << "ffmpeg with libaom-av1 not available";
  test::TempDir tmp;
  Fixture fx;
  fx.v3 = true;
  fx.frames = 16;
  const auto root = make_lerobot(tmp / "gr1_av1", fx);
  const fs::path video = root / "videos" / kCamera / "chunk-000" / "file-000.mp4";
  const fs::path av1 = tmp / "av1.mp4";
  const std::string cmd = "ffmpeg -loglevel error -y -i " + video.string() +
                          " -c:v libaom-av1 -cpu-used 8 -g 2 -crf 30 -pix_fmt yuv420p " + av1.string();
  ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  fs::rename(av1, video);
  ASSERT_EQ(io::probe_video(video.string()).codec, "av1");
  const auto ds = LeRobotDataset::open(root);
  const auto frames = ds->read_frames(1, {0, 9, 15});
  EXPECT_NEAR(test::mean_level(frames[0]), level(16), 3.0);
  EXPECT_NEAR(test::mean_level(frames[1]), level(25), 3.0);
  EXPECT_NEAR(test::mean_level(frames[2]), level(31), 3.0);
}

TEST(LeRobot, ClipsPutGr1ActionsInTheirSlot) {
  test::TempDir tmp;
  Fixture fx;
  fx.v3 = true;
  ClipConfig config;
  config.height = config.width = 16;
  ClipDataset dataset(open_dataset(make_lerobot(tmp / "gr1", fx)), config);
  EXPECT_EQ(dataset.source().format(), "lerobot-v3.0");
  const auto clip = dataset.read(1, make_window(2, 2, 13));  // steps 2, 4, ..., 28
  ASSERT_EQ(clip.actions.sizes(), (std::vector<int64_t>{12, 384}));
  EXPECT_TRUE(clip.has_actions);
  EXPECT_EQ(clip.actions.slice(1, 29).abs().sum().item<float>(), 0.f);  // nothing outside [0, 29)
  // Slot dim 7 = raw dim 22: min 0.22, max 129.22 -> a_n = 2 (a - min) / 129 - 1.
  for (int j = 0; j < 12; ++j) {
    const double step = 2 + 2 * (1 + j), base = 2 + 2 * (4 * (j / 4));
    EXPECT_NEAR(clip.actions[j][7].item<float>(), 2 * (step - base) / 129.0, 1e-5) << j;
  }
  for (int k = 0; k < 13; ++k) EXPECT_NEAR(test::mean_level(clip.video[k]), level(30 + 4 + 2 * k), 2.0) << k;
  EXPECT_EQ(test::error_message([&] {
              (void)dataset.store();
            }).find("lerobot-v3.0 dataset is not an episode store") != std::string::npos,
            true);
}

TEST(LeRobot, MalformedDataGivesErrorsNamingTheFile) {
  test::TempDir tmp;
  Fixture fx;
  fx.episodes = 1;
  fx.frames = 12;
  const fs::path episode_file = "data/chunk-000/episode_000000.parquet";
  const fs::path video_file = fs::path("videos/chunk-000") / kCamera / "episode_000000.mp4";

  {  // truncated parquet
    const auto root = make_lerobot(tmp / "truncated", fx);
    const std::string bytes = test::read_file(root / episode_file);
    std::ofstream(root / episode_file, std::ios::binary | std::ios::trunc)
        << bytes.substr(0, bytes.size() / 2);
    const auto ds = LeRobotDataset::open(root);
    EXPECT_EQ(test::error_message([&] { ds->read_arrays(0); }),
              (root / episode_file).string() + ": not a parquet file (missing PAR1 magic; truncated?)");
  }
  {  // wrong column type: action stored as a scalar float
    const auto root = make_lerobot(tmp / "wrongtype", fx);
    io::ParquetWriter w;
    w.add_f32("action", std::vector<float>(12, 1.f));
    w.add_f32("timestamp", std::vector<float>(12, 0.f));
    w.add_i64("episode_index", std::vector<int64_t>(12, 0));
    w.write(root / episode_file);
    const auto ds = LeRobotDataset::open(root);
    EXPECT_EQ(test::error_message([&] { ds->read_arrays(0); }),
              (root / episode_file).string() + ": column 'action' is not a list column");
  }
  {  // missing video
    const auto root = make_lerobot(tmp / "novideo", fx);
    fs::remove(root / video_file);
    const auto ds = LeRobotDataset::open(root);
    EXPECT_EQ(test::error_message([&] { ds->read_frames(0, {0}); }),
              (root / video_file).string() + ": video file missing (episode 0)");
  }
  {  // timestamps beyond the video
    const auto root = make_lerobot(tmp / "late", fx);
    auto w = data_table(fx, 0, 1, {});
    io::ParquetWriter shifted;
    std::vector<float> ts;
    for (int k = 0; k < 12; ++k) ts.push_back(static_cast<float>(k / kFps + 5.0));
    std::vector<std::optional<std::vector<float>>> action(12, std::vector<float>(kRawDim, 0.f));
    shifted.add_list_f32("action", action);
    shifted.add_f32("timestamp", ts);
    shifted.add_i64("episode_index", std::vector<int64_t>(12, 0));
    shifted.write(root / episode_file);
    const auto ds = LeRobotDataset::open(root);
    const std::string message = test::error_message([&] { ds->read_frames(0, {3}); });
    EXPECT_EQ(
        message.rfind(
            (root / video_file).string() + ": timestamp 5.150000 s of episode 0 is outside the video", 0),
        0u)
        << message;
  }
  {  // bad modality.json
    const auto root = make_lerobot(tmp / "badmodality", fx);
    auto m = gr1_modality();
    m["action"]["left_arm"]["end"] = -3;
    write_json(root / "meta" / "modality.json", m);
    EXPECT_EQ(test::error_message([&] { LeRobotDataset::open(root); }),
              (root / "meta" / "modality.json").string() + ": action.left_arm: bad range [0, -3)");
    m["action"]["left_arm"]["end"] = 50;
    write_json(root / "meta" / "modality.json", m);
    EXPECT_EQ(test::error_message([&] { LeRobotDataset::open(root); }),
              (root / "meta" / "modality.json").string() +
                  ": action.left_arm ends at 50 beyond the 44-d action feature");
    m["action"].erase("waist");
    m["action"]["left_arm"]["end"] = 7;
    write_json(root / "meta" / "modality.json", m);
    EXPECT_EQ(test::error_message([&] { LeRobotDataset::open(root); }),
              root.string() + ": modality has no action key 'waist' needed for gr1");
  }
  {  // episode table and data disagree
    const auto root = make_lerobot(tmp / "short", fx);
    std::ofstream(root / "meta" / "episodes.jsonl", std::ios::trunc)
        << nlohmann::json{{"episode_index", 0}, {"tasks", {"x"}}, {"length", 13}}.dump() << "\n";
    const auto ds = LeRobotDataset::open(root);
    EXPECT_EQ(test::error_message([&] { ds->read_arrays(0); }),
              (root / episode_file).string() + ": episode 0 has 12 rows, the episode table says 13");
  }
}

TEST(LeRobot, EpisodeStatsFallbackWhenStatsJsonIsMissing) {
  test::TempDir tmp;
  Fixture fx;
  fx.frames = 14;
  const auto root = make_lerobot(tmp / "gr1", fx);
  fs::remove(root / "meta" / "stats.json");
  std::ofstream out(root / "meta" / "episodes_stats.jsonl");
  for (int e = 0; e < 2; ++e) {
    std::vector<float> mn(kRawDim), mx(kRawDim), mean(kRawDim), sd(kRawDim, 0.f);
    for (int d = 0; d < kRawDim; ++d)
      mn[d] = raw_action(e, 0, d), mx[d] = raw_action(e, 13, d), mean[d] = 100.f * e;
    out << nlohmann::json{{"episode_index", e},
                          {"stats",
                           {{"action",
                             {{"min", mn}, {"max", mx}, {"mean", mean}, {"std", sd}, {"count", {14}}}}}}}
               .dump()
        << "\n";
  }
  out.close();
  const auto ds = LeRobotDataset::open(root);
  ASSERT_TRUE(ds->info().action_stats.has_value());
  EXPECT_FLOAT_EQ(ds->info().action_stats->min[0], 0.f);
  EXPECT_FLOAT_EQ(ds->info().action_stats->max[0], raw_action(1, 13, 0));
  EXPECT_NEAR(ds->info().action_stats->mean[0], 50.f, 1e-4);
  EXPECT_NEAR(ds->info().action_stats->std[0], 50.f, 1e-3);  // pooled: two point masses at 0 and 100
}

TEST(LeRobot, DataInfoJsonForV21AndV30) {
  test::TempDir tmp;
  Fixture fx;
  fx.frames = 14;
  make_lerobot(tmp / "a", fx);
  fx.v3 = true;
  make_lerobot(tmp / "b", fx);
  for (const char* name : {"a", "b"}) {
    const auto r = test::run_dojo("data info " + (tmp / name).string() + " --json");
    ASSERT_EQ(r.exit_code, 0) << r.output;
    const auto j = nlohmann::json::parse(r.output);
    EXPECT_EQ(j.at("format"), std::string(name) == "a" ? "lerobot-v2.1" : "lerobot-v3.0");
    EXPECT_EQ(j.at("episodes"), 2);
    EXPECT_EQ(j.at("frames"), 28);
    EXPECT_EQ(j.at("fps"), kFps);
    EXPECT_EQ(j.at("action_dim"), 29);
    EXPECT_EQ(j.at("action_slot"), "gr1");
    EXPECT_EQ(j.at("cameras"), nlohmann::json({kCamera}));
    EXPECT_EQ(j.at("tasks"), nlohmann::json(kTasks));
    EXPECT_EQ(j.at("robot"), "gr1");
  }
}

TEST(DataConvert, LeRobotToEpisodeFormatIsResumable) {
  test::TempDir tmp;
  Fixture fx;
  fx.frames = 14;
  const auto src = make_lerobot(tmp / "gr1", fx);
  const std::string cmd = "data convert " + src.string() + " " + (tmp / "out").string() + " --size 16x16";
  auto r = test::run_dojo(cmd);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("2 episodes converted, 0 kept"), std::string::npos) << r.output;
  const auto store = EpisodeStore::open(tmp / "out");
  EXPECT_EQ(store.info().action_slot, "gr1");
  EXPECT_EQ(store.info().action_dim, 29);
  EXPECT_EQ(store.info().height, 16);
  ASSERT_TRUE(store.info().action_stats.has_value());
  EXPECT_FLOAT_EQ(store.info().action_stats->max[7], raw_action(1, 13, 22));
  const auto episode = store.load(1);
  EXPECT_FLOAT_EQ(episode.actions[3][7].item<float>(), raw_action(1, 3, 22));
  EXPECT_NEAR(test::mean_level(episode.frames[5]), level(14 + 5), 2.0);
  EXPECT_EQ(episode.meta.at("task"), "wave");
  // A rerun keeps what is there; other options are refused.
  r = test::run_dojo(cmd);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("0 episodes converted, 2 kept"), std::string::npos) << r.output;
  r = test::run_dojo(cmd + " --limit 1");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("holds a conversion with other options"), std::string::npos) << r.output;
}

TEST(DataConvert, StatsMatchLeRobotFieldNamesAndWrite) {
  test::TempDir tmp;
  Fixture fx;
  fx.frames = 14;
  const auto src = make_lerobot(tmp / "gr1", fx);
  fs::remove(src / "meta" / "stats.json");
  EXPECT_FALSE(LeRobotDataset::open(src)->info().action_stats.has_value());
  const auto r = test::run_dojo("data stats " + src.string() + " --json --write");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto j = nlohmann::json::parse(r.output.substr(r.output.find('{')));
  ASSERT_TRUE(j.contains("action") && j.contains("observation.state"));
  EXPECT_EQ(j.at("action").at("min").size(), 44u);
  EXPECT_FLOAT_EQ(j.at("action").at("min")[3].get<float>(), raw_action(0, 0, 3));
  EXPECT_FLOAT_EQ(j.at("action").at("max")[3].get<float>(), raw_action(1, 13, 3));
  EXPECT_NEAR(j.at("action").at("mean")[0].get<double>(), 56.5, 1e-4);  // (0..13 and 100..113) / 28
  EXPECT_EQ(j.at("action").at("count")[0], 28);
  // Written to meta/stats.json, so the dataset now trains.
  const auto ds = LeRobotDataset::open(src);
  ASSERT_TRUE(ds->info().action_stats.has_value());
  EXPECT_FLOAT_EQ(ds->info().action_stats->max[7], raw_action(1, 13, 22));
}

}  // namespace dojo::data

namespace dojo::data {

// Background workers read a LeRobot source (shared, cached parquet) and a video folder in one
// mixture: robot clips carry GR-1 actions, human clips the latent mask.
TEST(LeRobot, PrefetchLoaderMixesFormats) {
  test::TempDir tmp;
  Fixture fx;
  fx.v3 = true;
  fx.frames = 20;
  make_lerobot(tmp / "gr1", fx);
  fs::create_directories(tmp / "hv");
  io::VideoWriterOptions vopt;
  vopt.fps = 15;
  io::write_video((tmp / "hv" / "clip.mp4").string(), grey_frames(0, 20), vopt);
  ClipConfig config;
  config.height = config.width = 16;
  config.strides = {1};
  auto mixture = std::make_shared<ClipMixture>();
  mixture->add(std::make_shared<ClipDataset>(open_dataset(tmp / "gr1"), config), 1.0);
  mixture->add(std::make_shared<ClipDataset>(open_dataset(tmp / "hv"), config), 1.0);
  LoaderOptions options;
  options.batch_size = 4;
  options.workers = 2;
  options.seed = 5;
  PrefetchLoader loader(mixture, options);
  int robot = 0, human = 0;
  for (int b = 0; b < 3; ++b) {
    const Batch batch = loader.next();
    ASSERT_EQ(batch.video.sizes(), (std::vector<int64_t>{4, 13, 16, 16, 3}));
    for (int i = 0; i < 4; ++i) {
      const bool has = batch.has_actions[i].item<bool>();
      has ? ++robot : ++human;
      const auto rows = batch.actions[i];  // [12, 384]
      if (has)
        EXPECT_EQ(rows.slice(1, 29).abs().sum().item<float>(), 0.f);
      else
        EXPECT_EQ(rows.slice(1, 352).sum().item<float>(), 12.f * 32.f);
    }
  }
  EXPECT_GT(robot, 0);
  EXPECT_GT(human, 0);
}

}  // namespace dojo::data

namespace dojo::data {

// `dojo data check` on LeRobot copies: each copy the converter refuses is reported with the file
// that is broken; an intact copy passes.
TEST(DataCheck, NamesTheBrokenFileOfEveryCopyTheConverterRefuses) {
  test::TempDir tmp;
  Fixture fx;
  fx.episodes = 1;
  fx.frames = 12;
  const fs::path episode_file = "data/chunk-000/episode_000000.parquet";
  const fs::path video_file = fs::path("videos/chunk-000") / kCamera / "episode_000000.mp4";
  {
    const auto root = make_lerobot(tmp / "intact", fx);
    EXPECT_EQ(check_episode(*open_dataset(root), 0), "");
    const auto result = test::run_dojo("data check " + root.string());
    EXPECT_EQ(result.exit_code, 0) << result.output;
    EXPECT_NE(result.output.find("1 episodes of lerobot-v2.1 checked, 0 bad"), std::string::npos)
        << result.output;
  }
  std::vector<std::pair<fs::path, fs::path>> broken;  // (copy, the file named)
  {
    const auto root = make_lerobot(tmp / "truncated_parquet", fx);
    const std::string bytes = test::read_file(root / episode_file);
    std::ofstream(root / episode_file, std::ios::binary | std::ios::trunc)
        << bytes.substr(0, bytes.size() / 2);
    broken.emplace_back(root, root / episode_file);
  }
  {
    const auto root = make_lerobot(tmp / "truncated_video", fx);
    const std::string bytes = test::read_file(root / video_file);
    std::ofstream(root / video_file, std::ios::binary | std::ios::trunc) << bytes.substr(0, bytes.size() / 3);
    broken.emplace_back(root, root / video_file);
  }
  {
    const auto root = make_lerobot(tmp / "missing_video", fx);
    fs::remove(root / video_file);
    broken.emplace_back(root, root / video_file);
  }
  {
    const auto root = make_lerobot(tmp / "short_table", fx);
    std::ofstream(root / "meta" / "episodes.jsonl", std::ios::trunc)
        << nlohmann::json{{"episode_index", 0}, {"tasks", {"x"}}, {"length", 13}}.dump() << "\n";
    broken.emplace_back(root, root / episode_file);
  }
  for (const auto& [root, file] : broken) {
    const auto source = open_dataset(root);  // `data info` opens every one of them
    EXPECT_NE(test::error_message(
                  [&] { convert_dataset(*source, tmp / ("converted_" + root.filename().string())); }),
              "(no error)")
        << root;
    const std::string problem = check_episode(*source, 0);
    EXPECT_NE(problem.find(file.string()), std::string::npos) << root << ": " << problem;
    const auto result = test::run_dojo("data check " + root.string());
    EXPECT_EQ(result.exit_code, 1) << result.output;
    EXPECT_NE(result.output.find(file.string()), std::string::npos) << result.output;
  }
}

}  // namespace dojo::data
