#include "recipes/teleop_check.h"

#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <fstream>

#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "data/episode_store.h"
#include "eval/keypoint_metrics.h"
#include "io/video.h"
#include "models/keypoint_probe.h"
#include "sim/episode.h"
#include "sim/renderer.h"
#include "sim/world.h"

namespace fs = std::filesystem;

namespace dojo::recipes {
namespace {

constexpr int64_t kArmKeypoints = 3;
constexpr double kUnchanged = 1e-6;  // a command value that moved less than this did not move

// actions.jsonl -> every step's raw command rows, in order: [R, w].
torch::Tensor read_raw_commands(const fs::path& path) {
  std::ifstream in(path);
  DOJO_CHECK(in.good(), path.string() + ": cannot read");
  std::vector<torch::Tensor> steps;
  std::string line;
  for (int64_t number = 1; std::getline(in, line); ++number) {
    if (line.empty()) continue;
    const auto where = path.string() + " line " + std::to_string(number);
    const auto j = nlohmann::json::parse(line, nullptr, false);
    DOJO_CHECK(!j.is_discarded() && j.is_object(), where + ": not a JSON object");
    DOJO_CHECK(j.contains("raw") && j["raw"].is_array() && !j["raw"].empty(),
               where + ": no 'raw' commands (a session driven by 384-d rows cannot be replayed)");
    std::vector<float> values;
    int64_t width = -1;
    for (const auto& row : j["raw"]) {
      DOJO_CHECK(row.is_array() && (width < 0 || static_cast<int64_t>(row.size()) == width),
                 where + ": 'raw' must be rows of equal width");
      width = static_cast<int64_t>(row.size());
      for (const auto& x : row) {
        DOJO_CHECK(x.is_number() && std::isfinite(x.get<double>()), where + ": 'raw' values must be finite");
        values.push_back(x.get<float>());
      }
    }
    steps.push_back(torch::tensor(values).view({-1, width}));
  }
  DOJO_CHECK(!steps.empty(), path.string() + ": no steps recorded");
  return torch::cat(steps);  // [R, w]
}

size_t find_episode(const data::EpisodeStore& store, const std::string& id) {
  const auto& eps = store.info().episodes;
  for (size_t i = 0; i < eps.size(); ++i)
    if (eps[i].id == id) return i;
  throw Error(store.dir().string() + ": no episode '" + id + "' (the recording started from it)");
}

// Replays the rows in DojoSim from the episode's scene: arm keypoints [1 + R, 3, 3] (u, v, in_view)
// and the rendered frames [1 + R, H, W, 3].
struct Replay {
  torch::Tensor keypoints, frames;
};
Replay replay(sim::World& world, const torch::Tensor& rows) {
  const int64_t n = rows.size(0) + 1;
  Replay out;
  out.keypoints = torch::zeros({n, kArmKeypoints, 3});
  sim::Renderer renderer;
  std::vector<torch::Tensor> rendered;
  const auto record = [&](int64_t t) {
    const auto points = world.keypoints();
    for (int64_t k = 0; k < kArmKeypoints; ++k)
      out.keypoints[t][k] = torch::tensor({static_cast<float>(points[k].u), static_cast<float>(points[k].v),
                                           points[k].in_view ? 1.0f : 0.0f});
    auto rgb = renderer.render(world);
    rendered.push_back(
        torch::from_blob(rgb.data(), {world.spec().height, world.spec().width, 3}, torch::kUInt8).clone());
  };
  record(0);
  const auto r = rows.to(torch::kFloat64).contiguous();
  for (int64_t i = 0; i < r.size(0); ++i) {
    world.step(std::vector<double>(r[i].data_ptr<double>(), r[i].data_ptr<double>() + r.size(1)));
    record(i + 1);
  }
  out.frames = torch::stack(rendered);
  return out;
}

// Runs of rows in which exactly one dimension moves, the same way every row. `previous`: the
// command in force before row 0 [w].
std::vector<HeldKey> held_keys(const torch::Tensor& rows, const torch::Tensor& previous,
                               const std::vector<std::string>& names) {
  const auto before = torch::cat({previous.view({1, -1}), rows.narrow(0, 0, rows.size(0) - 1)});
  const auto delta = (rows - before).contiguous();  // [R, w]
  std::vector<HeldKey> keys;
  int64_t open_dim = -1, open_sign = 0;
  for (int64_t r = 0; r < delta.size(0); ++r) {
    int64_t dim = -1, sign = 0, moved = 0;
    for (int64_t d = 0; d < delta.size(1); ++d) {
      const float x = delta[r][d].item<float>();
      if (std::abs(x) <= kUnchanged) continue;
      ++moved;
      dim = d;
      sign = x > 0 ? 1 : -1;
    }
    if (moved != 1) dim = -1;
    if (dim >= 0 && dim == open_dim && sign == open_sign) {
      ++keys.back().rows;
    } else if (dim >= 0) {
      HeldKey k;
      k.dimension = dim < static_cast<int64_t>(names.size()) ? names[dim] : "dim" + std::to_string(dim);
      k.sign = static_cast<int>(sign);
      k.first_row = r;
      k.rows = 1;
      keys.push_back(k);
    }
    open_dim = dim;
    open_sign = sign;
  }
  // A single row is a tap or a joint reaching its limit, not a hold.
  keys.erase(std::remove_if(keys.begin(), keys.end(), [](const HeldKey& k) { return k.rows < 2; }),
             keys.end());
  return keys;
}

double share(const torch::Tensor& mask) {
  return mask.numel() ? mask.to(torch::kFloat64).mean().item<double>() : 0;
}

}  // namespace

torch::Tensor unchanged_scene_share(const torch::Tensor& stream, const torch::Tensor& replay) {
  DOJO_CHECK(stream.sizes() == replay.sizes() && stream.dim() == 4 && stream.size(3) == 3,
             "unchanged_scene_share: stream and replay must be [T, H, W, 3] of one size");
  const auto s = stream.to(torch::kFloat64), r = replay.to(torch::kFloat64);
  const auto unchanged = (r - r.narrow(0, 0, 1)).abs().amax(-1).le(12);  // [T, H, W]
  const auto kept = (s - r).abs().mean(-1).le(kSceneTolerance) & unchanged;
  return kept.sum({1, 2}).to(torch::kFloat64) / unchanged.sum({1, 2}).clamp_min(1).to(torch::kFloat64);
}

nlohmann::json TeleopCheck::to_json() const {
  nlohmann::json held = nlohmann::json::array();
  for (const auto& k : keys)
    held.push_back({{"dimension", k.dimension},
                    {"sign", k.sign},
                    {"first_row", k.first_row},
                    {"rows", k.rows},
                    {"replay_motion_px", k.replay_motion},
                    {"stream_motion_px", k.stream_motion},
                    {"stream_found", k.stream_found},
                    {"counted", k.counted},
                    {"agrees", k.agrees}});
  return {
      {"episode", episode},
      {"frames", frames},
      {"seconds", seconds},
      {"arm_found", arm_found},
      {"arm_found_by_probe_alone", arm_found_by_probe_alone},
      {"scene_kept", scene_kept},
      {"scene_kept_first_100", scene_kept_first_100},
      {"scene_kept_last_100", scene_kept_last_100},
      {"scene_share", scene_share},
      {"arm_in_view", arm_in_view},
      {"arm_found_where_in_view", finite_or_null(arm_found_where_in_view)},
      {"arm_found_in_replay", finite_or_null(arm_found_in_replay)},
      {"arm_found_first_100", arm_found_first_100},
      {"arm_found_last_100", arm_found_last_100},
      {"arm_lost_frames", arm_lost_frames},
      {"keypoint_error_px", finite_or_null(keypoint_error_px)},
      {"detected", finite_or_null(detected)},
      {"held_keys", held},
      {"counted_keys", counted_keys},
      {"agreeing_keys", agreeing_keys},
      {"sign_agreement", finite_or_null(sign_agreement)},
      {"definitions",
       "scene kept: at least min_scene_share of the pixels the replay leaves as at its start are within 24 "
       "grey levels of the replay; arm found: the scene is kept and the probe says >= 2 of the arm's 3 "
       "keypoints are present (arm_found_by_probe_alone: the probe whatever the frame); a held key counts "
       "when the DojoSim replay moves the gripper >= min_motion_px over the hold, and agrees when both ends "
       "of the hold keep the scene, the probe finds the gripper there in the stream, and its displacement "
       "along the replay's direction is at least half min_motion_px; keypoint error and detection (within "
       "the radius) against the replay's keypoints"}};
}

TeleopCheck check_teleop_recording(const TeleopCheckOptions& o) {
  const auto session_path = (o.recording / "session.json").string();
  DOJO_CHECK(fs::exists(session_path), session_path + ": missing (is this a recording of `dojo serve`?)");
  const auto about = read_json_file(session_path);
  DOJO_CHECK(about.is_object(), session_path + ": not a JSON object");
  DOJO_CHECK(about.value("first_step", int64_t{-1}) == 0,
             session_path + ": the recording began after the stream's start (first_step " +
                 about.value("first_step", nlohmann::json()).dump() +
                 "); record from the start ('record': true in the start message, or the page's ?record=1)");
  DOJO_CHECK(about.contains("episode") && about["episode"].is_string() &&
                 !about["episode"].get<std::string>().empty(),
             session_path +
                 ": no 'episode' (a session from an uploaded image has no "
                 "scene to replay)");
  const fs::path data_dir = !o.data.empty() ? o.data : fs::path(about.value("data", std::string()));
  DOJO_CHECK(!data_dir.empty(), session_path + ": no 'data'; give --data");
  const auto store = data::EpisodeStore::open(data_dir);
  TeleopCheck out;
  out.episode = about["episode"].get<std::string>();
  const size_t episode_index = find_episode(store, out.episode);
  const auto episode_dir = store.episode_dir(episode_index).string();
  const auto episode = store.load_arrays(episode_index);
  DOJO_CHECK(episode.meta.contains("scene") && episode.actions.defined() && episode.actions.size(0) > 0,
             episode_dir + ": not a DojoSim robot episode (no scene or actions to replay)");

  const auto rows = read_raw_commands(o.recording / "actions.jsonl");  // [R, w]
  io::VideoReader reader((o.recording / "video.mp4").string());
  const auto stream = reader.read_all();  // [1 + R, H, W, 3]
  DOJO_CHECK(stream.size(0) == rows.size(0) + 1,
             (o.recording / "video.mp4").string() + ": " + std::to_string(stream.size(0)) +
                 " frames, but actions.jsonl has " + std::to_string(rows.size(0)) +
                 " command rows (expected rows + 1 frames)");
  out.frames = stream.size(0);
  out.seconds = static_cast<double>(rows.size(0)) / about.value("fps", 10.0);

  // The replay, from the scene at the episode's frame 0 (settled as the generator settles it).
  sim::World world(sim::scene_from_json(episode.meta["scene"]));
  world.hold(sim::EpisodeSpec{}.settle_steps);
  DOJO_CHECK(rows.size(1) == world.action_dim(),
             (o.recording / "actions.jsonl").string() + ": rows of " + std::to_string(rows.size(1)) +
                 " commands, DojoSim takes " + std::to_string(world.action_dim()));
  const auto names = world.command_names();
  const auto replayed = replay(world, rows);
  const auto& truth = replayed.keypoints;  // [1 + R, 3, 3]
  const int64_t height = stream.size(1), width = stream.size(2);
  if (episode.keypoints.defined() && episode.keypoints.size(0) > 0) {
    const auto recorded = episode.keypoints[0].view({-1, 3}).narrow(0, 0, kArmKeypoints);
    const double off = ((recorded.narrow(1, 0, 2) - truth[0].narrow(1, 0, 2)) *
                        torch::tensor({static_cast<float>(width), static_cast<float>(height)}))
                           .norm(2, 1)
                           .max()
                           .item<double>();
    DOJO_CHECK(off < 0.5, episode_dir + ": the replay does not start where the episode does (" +
                              std::to_string(off) +
                              " px off): another DojoSim version, or not this recording's data");
  }

  auto probe = models::load_keypoint_probe(o.probe);
  const auto found = models::detect_keypoints(probe, stream);
  const int64_t offset = models::keypoint_offset(probe->config(), "robot");
  const auto arm_present = [&](const models::KeypointOutput& k) {  // [T, 3]
    return k.presence.narrow(1, offset, kArmKeypoints).gt(0);
  };
  const auto present = arm_present(found);
  DOJO_CHECK(replayed.frames.sizes() == stream.sizes(),
             (o.recording / "video.mp4").string() + ": frames of " + std::to_string(height) + "x" +
                 std::to_string(width) + ", DojoSim renders this scene at " +
                 std::to_string(replayed.frames.size(1)) + "x" + std::to_string(replayed.frames.size(2)));
  const auto scene_share = unchanged_scene_share(stream, replayed.frames).contiguous();  // [T]
  const auto scene_kept = scene_share.ge(o.min_scene_share);
  out.scene_share.assign(scene_share.data_ptr<double>(),
                         scene_share.data_ptr<double>() + scene_share.numel());
  const auto probe_found = present.sum(1).ge(2);  // [T]
  const auto arm_found = probe_found & scene_kept;
  const auto arm_in_view = truth.select(2, 2).gt(0.5).sum(1).ge(2);  // [T]
  // The probe's own ceiling: on DojoSim's frames of the same commands it misses the arm sometimes too.
  const auto replay_found = arm_present(models::detect_keypoints(probe, replayed.frames)).sum(1).ge(2);
  out.arm_found_in_replay = share(replay_found.masked_select(arm_in_view));
  out.arm_found = share(arm_found);
  out.arm_found_by_probe_alone = share(probe_found);
  out.scene_kept = share(scene_kept);
  out.arm_in_view = share(arm_in_view);
  out.arm_found_where_in_view = arm_in_view.any().item<bool>() ? share(arm_found.masked_select(arm_in_view))
                                                               : std::numeric_limits<double>::quiet_NaN();
  const auto lost = (arm_in_view & ~arm_found).nonzero().view(-1).contiguous();
  out.arm_lost_frames.assign(lost.data_ptr<int64_t>(), lost.data_ptr<int64_t>() + lost.numel());
  const int64_t window = std::min<int64_t>(100, out.frames);
  out.arm_found_first_100 = share(arm_found.narrow(0, 0, window));
  out.arm_found_last_100 = share(arm_found.narrow(0, out.frames - window, window));
  out.scene_kept_first_100 = share(scene_kept.narrow(0, 0, window));
  out.scene_kept_last_100 = share(scene_kept.narrow(0, out.frames - window, window));
  const auto scores = eval::score_keypoints(found, offset, truth, height, width);
  out.keypoint_error_px = eval::nan_mean(scores.error);
  out.detected = eval::nan_mean(scores.detected);

  // Held keys: the gripper's motion from the frame the key went down to the frame after its last row.
  const auto scale = torch::tensor({static_cast<double>(width), static_cast<double>(height)});
  const auto stream_gripper = found.coords.select(1, offset).to(torch::kFloat64) * scale;  // [T, 2] px
  const auto replay_gripper = truth.select(1, 0).narrow(1, 0, 2).to(torch::kFloat64) * scale;
  const double min_motion = o.min_motion_px * std::min(height, width) / 64.0;
  out.keys = held_keys(rows, episode.actions[0].to(torch::kFloat32), names);
  for (auto& k : out.keys) {
    const int64_t a = k.first_row, b = k.first_row + k.rows;
    const auto d_replay = replay_gripper[b] - replay_gripper[a];
    const auto d_stream = stream_gripper[b] - stream_gripper[a];
    k.replay_motion = {d_replay[0].item<double>(), d_replay[1].item<double>()};
    k.stream_motion = {d_stream[0].item<double>(), d_stream[1].item<double>()};
    k.stream_found = present[a][0].item<bool>() && present[b][0].item<bool>() && scene_kept[a].item<bool>() &&
                     scene_kept[b].item<bool>();
    const bool replay_in_view = truth[a][0][2].item<float>() > 0.5f && truth[b][0][2].item<float>() > 0.5f;
    k.counted = replay_in_view && d_replay.norm().item<double>() >= min_motion;
    // Moving the replay's way means moving: the stream's displacement along the replay's direction
    // must be at least half the smallest counted motion (a frozen stream's probe jitter is not).
    const double along =
        (d_replay * d_stream).sum().item<double>() / std::max(d_replay.norm().item<double>(), 1e-9);
    k.agrees = k.counted && k.stream_found && along >= 0.5 * min_motion;
    out.counted_keys += k.counted;
    out.agreeing_keys += k.agrees;
  }
  if (out.counted_keys > 0) out.sign_agreement = static_cast<double>(out.agreeing_keys) / out.counted_keys;

  if (!o.video.empty()) {
    static const std::vector<std::array<uint8_t, 3>> kColors = {{255, 60, 60}, {60, 220, 60}, {70, 140, 255}};
    constexpr int64_t kScale = 4;
    auto left = io::upscale_nearest(stream, kScale).clone();
    auto right = io::upscale_nearest(replayed.frames, kScale).clone();
    io::draw_markers(left, found.coords.narrow(1, offset, kArmKeypoints), present, kScale, kColors);
    io::draw_markers(right, truth.narrow(2, 0, 2), truth.select(2, 2).gt(0.5), kScale, kColors);
    io::write_comparison_video(o.video.string(), {left, right}, {"stream (probe)", "DojoSim replay"},
                               about.value("fps", 10.0));
    LOG_INFO("serve-check: side-by-side video ", o.video.string());
  }
  return out;
}

}  // namespace dojo::recipes
