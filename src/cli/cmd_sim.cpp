#include <torch/torch.h>
#include <CLI/CLI.hpp>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/error.h"
#include "io/video.h"
#include "recipes/dojosim_policies.h"
#include "sim/episode.h"
#include "sim/generate.h"
#include "sim/renderer.h"
#include "sim/scene.h"

namespace dojo::cli {
namespace {

std::string join(const std::vector<std::string>& items) {
  std::string out;
  for (const auto& s : items) out += (out.empty() ? "" : ", ") + s;
  return out;
}

void add_generate(CLI::App& sim) {
  auto* cmd =
      sim.add_subcommand("generate",
                         "Generate a DojoSim dataset (mp4 + actions/states + meta per episode, info.json "
                         "with statistics and splits). "
                         "Deterministic for a seed; re-running the same command resumes an interrupted run.");
  auto o = std::make_shared<sim::GenerateOptions>();
  auto out = std::make_shared<std::string>();
  auto size = std::make_shared<std::string>("64x64");
  auto json = std::make_shared<bool>(false);
  auto policies = std::make_shared<std::string>();
  add_out_option(cmd, *out, "dataset directory")->required();
  cmd->add_option("--embodiment", o->embodiment, "human (action-free video) or robot (joint actions)")
      ->check(CLI::IsMember({"human", "robot"}))
      ->capture_default_str();
  cmd->add_option("--split", o->split,
                  "train | " + join({"ood-objects", "counterfactual", "novel-background", "long-horizon"}) +
                      " (robot evaluation splits)")
      ->capture_default_str();
  cmd->add_option("--episodes,-n", o->episodes, "Number of episodes")->capture_default_str();
  cmd->add_option("--frames", o->frames,
                  "Frames per episode at 10 Hz (0 = split default: 64, long-horizon 600)")
      ->capture_default_str();
  cmd->add_option("--size", *size, "Frame size HEIGHTxWIDTH")->capture_default_str();
  add_seed_option(cmd, o->seed);
  add_workers_option(cmd, o->workers);
  cmd->add_option("--val-fraction", o->val_fraction, "Robot train split: share of episodes marked 'val'")
      ->capture_default_str();
  cmd->add_option("--skills", o->skills,
                  "Human: restrict to these skills (push, poke, pat, sweep, pick_place, ...)");
  cmd->add_option("--quality", o->quality, "Robot bin policy: expert, good, medium, poor (default: a mix)");
  cmd->add_option(
         "--play-fraction", o->play_fraction,
         "Robot train split: share of episodes moving the arm at random (play) instead of the bin task")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  cmd->add_option("--play-behaviors", o->play_behaviors,
                  "Robot train split: the play episodes' behaviours, in turn (random_motion, teleop_play: an "
                  "operator holding the teleoperation page's keys); default random_motion")
      ->check(CLI::IsMember(sim::play_behavior_names()))
      ->delimiter(',');
  cmd->add_option("--policies", *policies,
                  "Robot train split: the episodes run the policies of this policy-set file in turn (as "
                  "`policy eval --policies`; scripted policies only), or 'default' for the built-in set "
                  "of 13, instead of the expert/good/medium mix");
  cmd->add_option("--cameras", o->cameras,
                  "Cameras recorded beside the egocentric one, each as CAMERA.mp4 (side: a fixed view from "
                  "the table's right); multi-view training tiles them (--views ego,side)")
      ->check(CLI::IsMember({"side"}))
      ->delimiter(',');
  auto video_format = std::make_shared<std::string>("mp4");
  add_video_format_option(cmd, *video_format);
  add_json_option(cmd, *json);
  cmd->callback([=] {
    set_action([=] {
      const auto [h, w] = parse_size(*size);
      o->height = static_cast<int>(h);
      o->width = static_cast<int>(w);
      o->video_format = data::video_format_from_string(*video_format, "--video-format");
      if (!policies->empty()) {
        const auto specs =
            *policies == "default" ? recipes::default_policy_set() : recipes::read_policy_set(*policies);
        for (const auto& spec : specs) {
          if (!spec.scripted())
            throw UsageError(*policies + ": policy '" + spec.name +
                             "' is not scripted; only scripted policies can generate data");
          o->policies.push_back({spec.name, recipes::scripted_policy_options(spec)});
        }
      }
      const auto summary = sim::generate_dataset(*out, *o);
      nlohmann::json j = {
          {"out", *out},
          {"generated", summary.generated},
          {"reused", summary.reused},
          {"frames", summary.frames},
          {"seconds", summary.seconds},
          {"frames_per_second", summary.seconds > 0 ? summary.frames / summary.seconds : 0.0}};
      if (!std::isnan(summary.mean_success)) j["mean_success"] = summary.mean_success;
      if (*json) {
        std::printf("%s\n", j.dump(2).c_str());
      } else {
        std::printf("%s: %d episodes generated, %d reused, %lld frames in %.1f s (%.1f frames/s)\n",
                    out->c_str(), summary.generated, summary.reused, static_cast<long long>(summary.frames),
                    summary.seconds, summary.seconds > 0 ? summary.frames / summary.seconds : 0.0);
        if (!std::isnan(summary.mean_success))
          std::printf("mean bin-task success: %.3f\n", summary.mean_success);
      }
      return 0;
    });
  });
}

void add_render(CLI::App& sim) {
  auto* cmd = sim.add_subcommand(
      "render", "Run one episode and write it as an mp4 (and optionally PNG frames) to look at");
  auto embodiment = std::make_shared<std::string>("robot");
  auto out = std::make_shared<std::string>();
  auto size = std::make_shared<std::string>("240x320");
  auto seed = std::make_shared<uint64_t>(0);
  auto steps = std::make_shared<int>(64);
  auto behavior = std::make_shared<std::string>("bin_pick");
  auto quality = std::make_shared<std::string>("expert");
  cmd->add_option("--embodiment", *embodiment, "human or robot")
      ->check(CLI::IsMember({"human", "robot"}))
      ->capture_default_str();
  add_out_option(cmd, *out, "mp4 file")->required();
  cmd->add_option("--size", *size, "Frame size HEIGHTxWIDTH")->capture_default_str();
  add_seed_option(cmd, *seed);
  cmd->add_option("--steps", *steps, "Control steps (frames) at 10 Hz")->capture_default_str();
  cmd->add_option("--behavior", *behavior, "Robot: bin_pick, pat, reach_miss, push, random_motion, idle")
      ->capture_default_str();
  cmd->add_option("--quality", *quality, "Robot bin policy: expert, good, medium, poor")
      ->capture_default_str();
  cmd->callback([=] {
    set_action([=] {
      const auto [h, w] = parse_size(*size);
      sim::SceneSampling sampling;
      sampling.height = static_cast<int>(h);
      sampling.width = static_cast<int>(w);
      const auto emb = sim::parse_embodiment(*embodiment);
      sim::EpisodeSpec spec;
      spec.scene = sim::sample_scene(emb, sampling, *seed);
      spec.controller = sim::default_controller(emb);
      if (emb == sim::Embodiment::kRobot) {
        spec.controller.robot.behavior = sim::parse_robot_behavior(*behavior);
        spec.controller.robot.quality = sim::PolicyQuality::preset(*quality);
      }
      spec.num_steps = *steps;
      spec.seed = *seed;
      const auto record = sim::run_episode(spec);
      auto frames = torch::empty({static_cast<int64_t>(record.frames.size()), record.height, record.width, 3},
                                 torch::kUInt8);  // [T, H, W, 3]
      for (size_t t = 0; t < record.frames.size(); ++t)
        std::memcpy(frames[t].data_ptr<uint8_t>(), record.frames[t].data(), record.frames[t].size());
      io::VideoWriterOptions options;
      options.fps = 10;
      io::write_video(*out, frames, options);
      std::printf("%s: %zu frames, task \"%s\"", out->c_str(), record.frames.size(),
                  record.meta.value("task", "").c_str());
      if (!std::isnan(record.success)) std::printf(", success %.2f", record.success);
      std::printf("\n");
      return 0;
    });
  });
}

}  // namespace

void register_sim(CLI::App& app) {
  auto* sim =
      app.add_subcommand("sim", "DojoSim: the built-in MuJoCo tabletop world (human hand and robot arm)");
  sim->require_subcommand(1);
  add_generate(*sim);
  add_render(*sim);
}

}  // namespace dojo::cli
