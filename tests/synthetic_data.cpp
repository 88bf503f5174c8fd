#include "synthetic_data.h"

#include <torch/torch.h>

#include <cstdio>

#include "data/actions.h"
#include "data/episode_store.h"

namespace dojo::test {

void write_synthetic_dataset(const std::filesystem::path& dir, const SyntheticOptions& o) {
  const bool robot = o.embodiment == "robot";
  const int64_t T = o.frames, S = o.size, side = std::max<int64_t>(3, S / 5);
  data::DatasetInfo info;
  info.name = dir.filename().string();
  info.embodiment = robot ? data::Embodiment::kRobot : data::Embodiment::kHuman;
  info.height = info.width = o.size;
  info.generator = {{"engine", "synthetic"}, {"seed", o.seed}};
  data::StatsAccumulator action_stats, state_stats;
  for (int e = 0; e < o.episodes; ++e) {
    auto gen = at::detail::createCPUGenerator(o.seed * 1000 + static_cast<uint64_t>(e));
    // A smooth random path of the block's top-left corner in [0, 1]^2, one point per frame.
    const auto start = torch::rand({2}, gen), goal = torch::rand({2}, gen);
    const auto s = torch::linspace(0, 1, T).unsqueeze(1);                      // [T, 1]
    const auto path = start + (goal - start) * (3 * s.pow(2) - 2 * s.pow(3));  // [T, 2]
    const auto table = torch::rand({3}, gen) * 0.5 + 0.3;
    const auto block = robot ? torch::tensor({0.15f, 0.15f, 0.2f}) : torch::tensor({0.9f, 0.7f, 0.6f});
    auto frames = torch::empty({T, S, S, 3}, torch::kFloat);
    auto keypoints = torch::ones({T, 3, 3});  // (u, v, in_view): centre, top-left, bottom-right
    for (int64_t t = 0; t < T; ++t) {
      frames[t].copy_(table.expand({S, S, 3}));
      const int64_t y = static_cast<int64_t>(path[t][0].item<double>() * static_cast<double>(S - side));
      const int64_t x = static_cast<int64_t>(path[t][1].item<double>() * static_cast<double>(S - side));
      frames[t].narrow(0, y, side).narrow(1, x, side).copy_(block.expand({side, side, 3}));
      const double s = static_cast<double>(S);
      const double left = x / s, top = y / s, right = (x + side) / s, bottom = (y + side) / s;
      keypoints[t][0][0] = 0.5 * (left + right), keypoints[t][0][1] = 0.5 * (top + bottom);
      keypoints[t][1][0] = left, keypoints[t][1][1] = top;
      keypoints[t][2][0] = right, keypoints[t][2][1] = bottom;
    }
    data::EpisodeData ep;
    ep.frames = (frames * 255).round().to(torch::kUInt8);
    ep.keypoints = keypoints.view({T, 9});
    if (o.side_camera) ep.views.push_back({"side", ep.frames.flip({2}).contiguous()});
    // Commands: action[t] moves the block to frame t + 1's position (the LeRobot convention).
    const auto next = torch::cat({path.slice(0, 1), path.slice(0, T - 1)}, 0);  // [T, 2]
    const auto command = torch::cat({next, torch::zeros({T, 4})}, 1);           // [T, 6]
    if (robot) {
      ep.actions = command;
      ep.states = torch::cat({path, torch::zeros({T, 4})}, 1);
      action_stats.add(ep.actions);
      state_stats.add(ep.states);
    } else {
      ep.hidden_motion = command;
    }
    const std::string split = e >= o.episodes - o.val_episodes ? "val" : "train";
    ep.meta = {
        {"embodiment", o.embodiment}, {"task", robot ? "move the block" : "move the hand"}, {"split", split}};
    char id[16];
    std::snprintf(id, sizeof id, "%06d", e);
    data::write_episode(dir / "episodes" / id, ep, 10.0, o.video_format);
    info.episodes.push_back({id, T, split, ep.meta["task"]});
  }
  info.keypoint_names = {"centre", "top_left", "bottom_right"};
  if (o.side_camera) info.cameras = {"ego", "side"};
  info.video_format = o.video_format;
  if (robot) {
    info.action_stats = action_stats.finish();
    info.state_stats = state_stats.finish();
    info.action_dim = info.state_dim = 6;
    info.action_names = info.state_names = {"y", "x", "a", "b", "c", "d"};
    info.action_slot = data::slots::kDojoSimRobot.name;
  }
  data::write_dataset_info(dir, info);
}

}  // namespace dojo::test
