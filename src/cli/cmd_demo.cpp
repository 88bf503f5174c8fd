// `dojo demo`: the end-to-end job on the built-in world. It runs every stage of the pipeline
// that exists, on DojoSim data small enough for a laptop CPU, and leaves files to look at.
#include <torch/torch.h>
#include <CLI/CLI.hpp>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/log.h"
#include "data/clip_loader.h"
#include "data/episode_store.h"
#include "sim/generate.h"

namespace fs = std::filesystem;

namespace dojo::cli {
namespace {

struct DemoOptions {
  std::string out = "dojo_demo";
  int episodes = 8;
  int frames = 64;
  uint64_t seed = 0;
  int workers = 0;
};

int run_demo(const DemoOptions& o) {
  const fs::path out = o.out;
  fs::create_directories(out);
  const auto start = std::chrono::steady_clock::now();
  nlohmann::json report;

  // Stage 1: the world. Human video without actions, robot episodes with joint actions.
  LOG_INFO("[1/3] DojoSim: generating human and robot episodes into ", out.string());
  sim::GenerateOptions human;
  human.embodiment = "human";
  human.episodes = o.episodes;
  human.frames = o.frames;
  human.seed = o.seed;
  human.workers = o.workers;
  const auto human_summary = sim::generate_dataset(out / "human", human);
  sim::GenerateOptions robot = human;
  robot.embodiment = "robot";
  robot.seed = o.seed + 1;
  const auto robot_summary = sim::generate_dataset(out / "robot", robot);
  report["human"] = {
      {"episodes", o.episodes}, {"generated", human_summary.generated}, {"seconds", human_summary.seconds}};
  report["robot"] = {{"episodes", o.episodes},
                     {"generated", robot_summary.generated},
                     {"seconds", robot_summary.seconds},
                     {"mean_bin_success", robot_summary.mean_success}};

  // Stage 2: look at it.
  LOG_INFO("[2/3] previews: ", (out / "preview_human.mp4").string(), ", ",
           (out / "preview_robot.mp4").string());
  data::write_preview_video(data::EpisodeStore::open(out / "human"), out / "preview_human.mp4", 4, 2);
  data::write_preview_video(data::EpisodeStore::open(out / "robot"), out / "preview_robot.mp4", 4, 2);

  // Stage 3: the clip pipeline every trainer consumes, as a 1:1 human/robot mixture.
  LOG_INFO("[3/3] clip pipeline: human:robot = 1:1 mixture, 13-frame clips, 384-d actions");
  auto mixture = std::make_shared<data::ClipMixture>();
  mixture->add(
      std::make_shared<data::ClipDataset>(data::EpisodeStore::open(out / "human"), data::ClipConfig{}, "all"),
      1.0);
  mixture->add(std::make_shared<data::ClipDataset>(data::EpisodeStore::open(out / "robot"),
                                                   data::ClipConfig{}, "train"),
               1.0);
  data::LoaderOptions loader_options;
  loader_options.batch_size = 4;
  loader_options.workers = 2;
  loader_options.seed = o.seed;
  data::PrefetchLoader loader(mixture, loader_options);
  const auto loader_start = std::chrono::steady_clock::now();
  int with_actions = 0, clips = 0;
  data::Batch batch;
  for (int i = 0; i < 8; ++i) {
    batch = loader.next();
    with_actions += batch.has_actions.sum().item<int>();
    clips += static_cast<int>(batch.has_actions.size(0));
  }
  const double loader_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - loader_start).count();
  report["clips"] = {{"batches", 8},
                     {"video_shape", batch.video.sizes().vec()},
                     {"action_shape", batch.actions.sizes().vec()},
                     {"robot_clips", with_actions},
                     {"human_clips", clips - with_actions},
                     {"clips_per_second", clips / loader_seconds}};
  report["seconds"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  write_file_atomic(out / "demo.json", report.dump(2) + "\n");

  std::printf("\nDreamDojo.cpp demo finished in %.1f s. Outputs in %s/\n", report["seconds"].get<double>(),
              out.string().c_str());
  std::printf("  human/, robot/          DojoSim datasets (%d episodes each, %d frames, 64x64, 10 Hz)\n",
              o.episodes, o.frames);
  std::printf("  preview_*.mp4           episodes side by side: open them in a browser or video player\n");
  if (!std::isnan(robot_summary.mean_success))
    std::printf("  robot bin-task success  %.2f (scripted policies of mixed quality)\n",
                robot_summary.mean_success);
  std::printf(
      "  clip batches            video %s uint8, actions %s (%d robot / %d human clips, %.1f clips/s)\n",
      nlohmann::json(batch.video.sizes().vec()).dump().c_str(),
      nlohmann::json(batch.actions.sizes().vec()).dump().c_str(), with_actions, clips - with_actions,
      clips / loader_seconds);
  std::printf("  demo.json               this summary as JSON\n");
  std::printf("Re-running resumes: finished episodes are reused.\n");
  return 0;
}

}  // namespace

void register_demo(CLI::App& app) {
  auto* cmd = app.add_subcommand("demo",
                                 "Run the pipeline end to end on the built-in DojoSim world: generate human "
                                 "and robot episodes, write preview "
                                 "videos, and draw training clips through the clip pipeline");
  auto o = std::make_shared<DemoOptions>();
  cmd->add_option("--out,-o", o->out, "Output directory")->capture_default_str();
  cmd->add_option("--episodes,-n", o->episodes, "Episodes per embodiment")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  cmd->add_option("--frames", o->frames, "Frames per episode (10 Hz)")
      ->check(CLI::Range(14, 100000))
      ->capture_default_str();
  cmd->add_option("--seed", o->seed, "Random seed")->capture_default_str();
  cmd->add_option("--workers,-j", o->workers, "Parallel generation workers (0 = all cores)")
      ->capture_default_str();
  cmd->callback([o] { set_action([o] { return run_demo(*o); }); });
}

}  // namespace dojo::cli
