#include <CLI/CLI.hpp>
#include <cstdio>
#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/error.h"
#include "core/progress.h"
#include "data/embodiments.h"
#include "data/episode_source.h"
#include "data/episode_store.h"
#include "data/lerobot_export.h"

namespace dojo::cli {

void register_data(CLI::App& app) {
  auto* data = app.add_subcommand(
      "data", "Inspect, convert and check datasets (episode format, LeRobot, EgoDex, video folders)");
  data->require_subcommand(1);

  // Options every reading command shares: how to open a non-native format.
  auto add_open_options = [](CLI::App* cmd, std::shared_ptr<data::OpenOptions> o) {
    cmd->add_option("--embodiment", o->embodiment,
                    "LeRobot robot: auto (info.json's robot_type, never the path), gr1, g1, yam, agibot, a "
                    "robot of --embodiments, human, none")
        ->capture_default_str();
    cmd->add_option("--camera", o->camera, "LeRobot video key (default: the robot's camera, else the first)");
    cmd->add_flag("--skip-dreamdojo-names", o->skip_dreamdojo_names,
                  "Video folders: skip names with left/right/resize/pad, as DreamDojo's raw-video loader");
    add_views_options(cmd, o->views, o->view_layout, "read as one canvas, as multi-view training does");
  };

  auto* info_cmd = data->add_subcommand(
      "info", "Summarise a dataset of any format (episode format, LeRobot v2.x/v3.0, EgoDex, video folder)");
  auto dir = std::make_shared<std::string>();
  auto json = std::make_shared<bool>(false);
  auto info_open = std::make_shared<data::OpenOptions>();
  info_cmd->add_option("DIR", *dir, "Dataset directory")->required();
  add_json_option(info_cmd, *json);
  add_open_options(info_cmd, info_open);
  info_cmd->callback([=] {
    set_action([=] {
      const auto source = data::open_dataset(*dir, *info_open);
      const auto summary = source->describe();
      const auto& info = source->info();
      if (*json) {
        std::printf("%s\n", summary.dump(2).c_str());
      } else {
        std::printf("dataset      %s (%s, %s)\n", info.name.c_str(), source->format().c_str(),
                    data::to_string(info.embodiment).c_str());
        std::printf("episodes     %zu, %lld frames at %.4g fps, %dx%d\n", info.episodes.size(),
                    static_cast<long long>(info.total_frames()), info.fps, info.height, info.width);
        std::printf("actions      %d-d%s%s, state %d-d%s\n", info.action_dim,
                    info.action_slot.empty() ? "" : " in slot ", info.action_slot.c_str(), info.state_dim,
                    info.action_stats
                        ? ""
                        : (info.embodiment == data::Embodiment::kRobot ? " (no action stats)" : ""));
        if (!summary.at("cameras").empty())
          std::printf("cameras      %s\n", summary.at("cameras").dump().c_str());
        std::printf("tasks        %zu\n", summary.at("tasks").size());
        for (const auto& [split, count] : info.split_counts())
          std::printf("split        %-18s %lld episodes\n", split.c_str(), static_cast<long long>(count));
      }
      return 0;
    });
  });

  auto* convert_cmd = data->add_subcommand(
      "convert",
      "Write any dataset in our episode format (frames decoded once, actions in slot order) or, with --to "
      "lerobot, as a LeRobot v2.1 dataset; resumable");
  auto convert_src = std::make_shared<std::string>();
  auto convert_dst = std::make_shared<std::string>();
  auto convert_size = std::make_shared<std::string>();
  auto convert_to = std::make_shared<std::string>("episodes");
  auto convert_limit = std::make_shared<int64_t>(-1);
  auto convert_open = std::make_shared<data::OpenOptions>();
  auto lerobot = std::make_shared<data::LeRobotExportOptions>();
  auto convert_format = std::make_shared<std::string>("mp4");
  convert_cmd->add_option("SRC", *convert_src, "Source dataset directory")->required();
  convert_cmd->add_option("DST", *convert_dst, "Output directory")->required();
  convert_cmd->add_option("--to", *convert_to, "episodes (our format) or lerobot (LeRobot v2.1)")
      ->check(CLI::IsMember({"episodes", "lerobot"}))
      ->capture_default_str();
  convert_cmd->add_option("--size", *convert_size, "Centre-crop and resize frames to HxW (default: keep)");
  convert_cmd->add_option("--limit", *convert_limit, "Convert only the first N episodes");
  convert_cmd->add_option("--robot-type", lerobot->robot_type,
                          "--to lerobot: info.json's robot_type (required)");
  convert_cmd
      ->add_option("--video-name", lerobot->camera,
                   "--to lerobot: the camera's name (observation.images.NAME)")
      ->capture_default_str();
  add_video_format_option(convert_cmd, *convert_format);
  add_open_options(convert_cmd, convert_open);
  convert_cmd->callback([=] {
    set_action([=] {
      int height = 0, width = 0;
      if (!convert_size->empty()) {
        const auto [h, w] = parse_size(*convert_size);
        height = static_cast<int>(h);
        width = static_cast<int>(w);
      }
      if (*convert_to == "lerobot" && *convert_format != "mp4")
        throw UsageError(
            "data convert --to lerobot writes mp4 videos (LeRobot's format): drop --video-format");
      if (*convert_to == "lerobot" && lerobot->robot_type.empty())
        throw UsageError(
            "data convert --to lerobot needs --robot-type NAME (LeRobot readers find the robot there)");
      const auto source = data::open_dataset(*convert_src, *convert_open);
      const int64_t total = *convert_limit < 0
                                ? static_cast<int64_t>(source->size())
                                : std::min<int64_t>(*convert_limit, static_cast<int64_t>(source->size()));
      Progress progress("convert", total, "episodes");
      data::ConvertResult result;
      if (*convert_to == "lerobot") {
        auto options = *lerobot;
        options.height = height;
        options.width = width;
        options.limit = *convert_limit;
        result = data::export_lerobot(*source, *convert_dst, options, [&] { progress.advance(); });
      } else {
        data::ConvertOptions options;
        options.video_format = data::video_format_from_string(*convert_format, "--video-format");
        options.height = height;
        options.width = width;
        options.limit = *convert_limit;
        result = data::convert_dataset(*source, *convert_dst, options, [&] { progress.advance(); });
      }
      progress.finish();
      std::printf("%s: %lld episodes converted, %lld kept from an earlier run (%s -> %s)\n",
                  convert_dst->c_str(), static_cast<long long>(result.converted),
                  static_cast<long long>(result.kept), source->format().c_str(), convert_to->c_str());
      return 0;
    });
  });

  auto* embodiments_cmd = data->add_subcommand("embodiments",
                                               "Print the embodiment table (built-in robots and those of "
                                               "--embodiments FILE) in the file's JSON format");
  embodiments_cmd->callback([] {
    set_action([] {
      // One robot a line: the file's format, readable and ready to copy into a table.
      const auto list = data::embodiment_table().at("embodiments");
      std::printf("{\"embodiments\": [\n");
      for (size_t i = 0; i < list.size(); ++i)
        std::printf("  %s%s\n", list[i].dump().c_str(), i + 1 < list.size() ? "," : "");
      std::printf("]}\n");
      return 0;
    });
  });

  auto* stats_cmd = data->add_subcommand(
      "stats", "Per-dimension min/max/mean/std of actions and states (LeRobot stats.json field names)");
  auto stats_dir = std::make_shared<std::string>();
  auto stats_json = std::make_shared<bool>(false);
  auto stats_write = std::make_shared<bool>(false);
  auto stats_open = std::make_shared<data::OpenOptions>();
  stats_cmd->add_option("DIR", *stats_dir, "Dataset directory")->required();
  add_json_option(stats_cmd, *stats_json);
  stats_cmd->add_flag(
      "--write", *stats_write,
      "Store them: meta/stats.json for LeRobot (other keys kept), info.json for the episode format");
  add_open_options(stats_cmd, stats_open);
  stats_cmd->callback([=] {
    set_action([=] {
      const auto source = data::open_dataset(*stats_dir, *stats_open);
      const auto stats = data::compute_stats(*source);
      if (*stats_write) {
        const auto path = data::write_stats(*source, stats);
        std::fprintf(stderr, "wrote %s\n", path.string().c_str());
      }
      if (*stats_json) {
        std::printf("%s\n", stats.dump(2).c_str());
      } else {
        for (const auto& [name, s] : stats.items()) {
          std::printf("%s (%zu-d, %lld rows)\n", name.c_str(), s.at("min").size(),
                      static_cast<long long>(s.at("count")[0].get<int64_t>()));
          for (size_t d = 0; d < s.at("min").size(); ++d)
            std::printf("  %3zu  min %10.4g  max %10.4g  mean %10.4g  std %10.4g\n", d,
                        s.at("min")[d].get<double>(), s.at("max")[d].get<double>(),
                        s.at("mean")[d].get<double>(), s.at("std")[d].get<double>());
        }
        if (stats.empty()) std::printf("no actions or states (action-free dataset)\n");
      }
      return 0;
    });
  });

  auto* preview_cmd = data->add_subcommand(
      "preview",
      "Write an mp4 showing several episodes side by side, labelled with their task, to look at a dataset");
  auto preview_dir = std::make_shared<std::string>();
  auto preview_out = std::make_shared<std::string>();
  auto preview_count = std::make_shared<int>(4);
  auto preview_scale = std::make_shared<int>(2);
  auto preview_open = std::make_shared<data::OpenOptions>();
  auto preview_frames = std::make_shared<int64_t>(300);
  preview_cmd->add_option("DIR", *preview_dir, "Dataset directory (any format `data info` reads)")
      ->required();
  preview_cmd->add_option("--max-frames", *preview_frames, "Frames per episode at most (0 = all)")
      ->capture_default_str();
  add_open_options(preview_cmd, preview_open);
  add_out_option(preview_cmd, *preview_out, "mp4 file")->required();
  preview_cmd->add_option("--episodes,-n", *preview_count, "How many episodes (the first N)")
      ->capture_default_str();
  preview_cmd->add_option("--scale", *preview_scale, "Integer upscale of small frames (nearest neighbour)")
      ->check(CLI::Range(1, 8))
      ->capture_default_str();
  preview_cmd->callback([=] {
    set_action([=] {
      const auto source = data::open_dataset(*preview_dir, *preview_open);
      const size_t n = std::min<size_t>(source->size(), static_cast<size_t>(std::max(1, *preview_count)));
      data::write_preview_video(*source, *preview_out, n, *preview_scale, *preview_frames);
      std::printf("%s: %zu episodes of %s (%s)\n", preview_out->c_str(), n, source->root().string().c_str(),
                  source->format().c_str());
      return 0;
    });
  });

  auto* check_cmd = data->add_subcommand(
      "check",
      "Decode every episode and validate arrays (lengths, NaN, video frame counts); exit 1 on problems");
  auto check_dir = std::make_shared<std::string>();
  auto check_open = std::make_shared<data::OpenOptions>();
  check_cmd->add_option("DIR", *check_dir, "Dataset directory (any format `data info` reads)")->required();
  add_open_options(check_cmd, check_open);
  check_cmd->callback([=] {
    set_action([=] {
      const auto source = data::open_dataset(*check_dir, *check_open);
      Progress progress("check", static_cast<int64_t>(source->size()), "episodes");
      int bad = 0;
      for (size_t i = 0; i < source->size(); ++i) {
        const std::string problem = data::check_episode(*source, i);
        if (!problem.empty()) {
          ++bad;
          std::fprintf(stderr, "bad episode: %s\n", problem.c_str());
        }
        progress.advance();
      }
      progress.finish();
      std::printf("%zu episodes of %s checked, %d bad\n", source->size(), source->format().c_str(), bad);
      return bad == 0 ? 0 : 1;
    });
  });
}

}  // namespace dojo::cli
