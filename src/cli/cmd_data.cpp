#include <CLI/CLI.hpp>
#include <cstdio>
#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "core/error.h"
#include "core/progress.h"
#include "data/episode_store.h"

namespace dojo::cli {

void register_data(CLI::App& app) {
  auto* data = app.add_subcommand("data", "Inspect and check datasets in the DojoSim episode format");
  data->require_subcommand(1);

  auto* info_cmd = data->add_subcommand("info", "Summarise a dataset: episodes, frames, action dims, splits");
  auto dir = std::make_shared<std::string>();
  auto json = std::make_shared<bool>(false);
  info_cmd->add_option("DIR", *dir, "Dataset directory (holds info.json)")->required();
  info_cmd->add_flag("--json", *json, "Print JSON");
  info_cmd->callback([=] {
    set_action([=] {
      const auto store = data::EpisodeStore::open(*dir);
      const auto& info = store.info();
      nlohmann::json summary;
      summary["name"] = info.name;
      summary["embodiments"] = {data::to_string(info.embodiment)};
      summary["episodes"] = info.episodes.size();
      summary["frames"] = info.total_frames();
      summary["fps"] = info.fps;
      summary["height"] = info.height;
      summary["width"] = info.width;
      summary["action_dim"] = info.action_dim;
      summary["state_dim"] = info.state_dim;
      summary["action_slot"] = info.action_slot;
      summary["splits"] = info.split_counts();
      if (*json) {
        std::printf("%s\n", summary.dump(2).c_str());
      } else {
        std::printf("dataset      %s (%s)\n", info.name.c_str(), data::to_string(info.embodiment).c_str());
        std::printf("episodes     %zu, %lld frames at %.0f fps, %dx%d\n", info.episodes.size(),
                    static_cast<long long>(info.total_frames()), info.fps, info.height, info.width);
        std::printf("actions      %d-d%s%s, state %d-d\n", info.action_dim,
                    info.action_slot.empty() ? "" : " in slot ", info.action_slot.c_str(), info.state_dim);
        for (const auto& [split, count] : info.split_counts())
          std::printf("split        %-18s %lld episodes\n", split.c_str(), static_cast<long long>(count));
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
  preview_cmd->add_option("DIR", *preview_dir, "Dataset directory")->required();
  preview_cmd->add_option("--out,-o", *preview_out, "Output .mp4 path")->required();
  preview_cmd->add_option("--episodes,-n", *preview_count, "How many episodes (the first N)")
      ->capture_default_str();
  preview_cmd->add_option("--scale", *preview_scale, "Integer upscale of small frames (nearest neighbour)")
      ->check(CLI::Range(1, 8))
      ->capture_default_str();
  preview_cmd->callback([=] {
    set_action([=] {
      const auto store = data::EpisodeStore::open(*preview_dir);
      const size_t n = std::min<size_t>(store.size(), static_cast<size_t>(std::max(1, *preview_count)));
      data::write_preview_video(store, *preview_out, n, *preview_scale);
      std::printf("%s: %zu episodes of %s\n", preview_out->c_str(), n, store.dir().string().c_str());
      return 0;
    });
  });

  auto* check_cmd = data->add_subcommand(
      "check",
      "Decode every episode and validate arrays (lengths, NaN, video frame counts); exit 1 on problems");
  auto check_dir = std::make_shared<std::string>();
  check_cmd->add_option("DIR", *check_dir, "Dataset directory")->required();
  check_cmd->callback([=] {
    set_action([=] {
      const auto store = data::EpisodeStore::open(*check_dir);
      Progress progress("check", static_cast<int64_t>(store.size()), "episodes");
      int bad = 0;
      for (size_t i = 0; i < store.size(); ++i) {
        const std::string problem = store.check_episode(i);
        if (!problem.empty()) {
          ++bad;
          std::fprintf(stderr, "bad episode: %s\n", problem.c_str());
        }
        progress.advance();
      }
      progress.finish();
      std::printf("%zu episodes checked, %d bad\n", store.size(), bad);
      return bad == 0 ? 0 : 1;
    });
  });
}

}  // namespace dojo::cli
