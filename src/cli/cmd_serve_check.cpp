// `dojo serve-check`: does teleoperation hold? Replays a session recorded from its start frame
// (`dojo serve`, the page's ?record=1) in DojoSim and reads the streamed frames with the keypoint
// probe (recipes/teleop_check.h).
#include <CLI/CLI.hpp>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <memory>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "recipes/teleop_check.h"

namespace fs = std::filesystem;

namespace dojo::cli {
namespace {

struct ServeCheckArgs {
  std::string recording, data, probe, video, json_out;
  double min_motion_px = recipes::TeleopCheckOptions{}.min_motion_px;
  double min_scene_share = recipes::TeleopCheckOptions{}.min_scene_share;
  bool json = false;
};

int run_serve_check(const ServeCheckArgs& a) {
  recipes::TeleopCheckOptions o;
  o.recording = a.recording;
  o.data = a.data;
  o.probe = !a.probe.empty() ? fs::path(a.probe) : default_reference_dir() / "probe";
  DOJO_CHECK(fs::exists(o.probe / "config.json"), o.probe.string() + ": no keypoint probe (give --probe)");
  o.min_motion_px = a.min_motion_px;
  o.min_scene_share = a.min_scene_share;
  o.video = a.video;
  const auto r = recipes::check_teleop_recording(o);
  const auto j = r.to_json();
  if (!a.json_out.empty()) write_file_atomic(a.json_out, j.dump(2) + "\n");
  if (a.json) {
    std::printf("%s\n", j.dump().c_str());
    return 0;
  }
  std::printf("%s: %lld frames (%.1f s) from episode %s\n", a.recording.c_str(),
              static_cast<long long>(r.frames), r.seconds, r.episode.c_str());
  std::printf(
      "scene kept (>= %.0f %% of the replay's unchanged pixels shown) in %.1f %% of frames; first 100 frames "
      "%.1f %%, last 100 %.1f %%\n",
      100 * o.min_scene_share, 100 * r.scene_kept, 100 * r.scene_kept_first_100, 100 * r.scene_kept_last_100);
  std::printf(
      "arm found in a kept scene in %.1f %% of frames (by the probe alone %.1f %%; the DojoSim replay shows "
      "it in %.1f %%; found in %.1f %% of those, where the probe finds it in %.1f %% of the replay's own "
      "frames); first 100 frames %.1f %%, last 100 %.1f %%\n",
      100 * r.arm_found, 100 * r.arm_found_by_probe_alone, 100 * r.arm_in_view,
      100 * r.arm_found_where_in_view, 100 * r.arm_found_in_replay, 100 * r.arm_found_first_100,
      100 * r.arm_found_last_100);
  std::printf("keypoints against the replay: %.2f px mean error, %.1f %% within the detection radius\n",
              r.keypoint_error_px, 100 * r.detected);
  for (const auto& k : r.keys)
    std::printf("  %-12s %c %3lld rows: replay (%+5.1f, %+5.1f) px, stream (%+5.1f, %+5.1f) px  %s\n",
                k.dimension.c_str(), k.sign > 0 ? '+' : '-', static_cast<long long>(k.rows),
                k.replay_motion[0], k.replay_motion[1], k.stream_motion[0], k.stream_motion[1],
                !k.counted ? "not counted (replay barely moves)"
                : k.agrees ? "agrees"
                           : "disagrees");
  std::printf("held keys moving the gripper the replay's way: %lld of %lld counted (%.1f %%)\n",
              static_cast<long long>(r.agreeing_keys), static_cast<long long>(r.counted_keys),
              std::isfinite(r.sign_agreement) ? 100 * r.sign_agreement : 0.0);
  return 0;
}

}  // namespace

void register_serve_check(CLI::App& app) {
  auto a = std::make_shared<ServeCheckArgs>();
  auto* cmd = app.add_subcommand(
      "serve-check",
      "Score a teleoperation recording of `dojo serve` (recorded from the start): replay its commands in "
      "DojoSim; is the arm still there, and does each held key move it the replay's way?");
  cmd->add_option("recording", a->recording,
                  "The recording's directory (session.json, video.mp4, actions.jsonl)")
      ->required()
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--data", a->data, "The episodes the session started from (default: session.json's)");
  cmd->add_option("--probe", a->probe, "Keypoint probe (default: the reference set's)");
  cmd->add_option("--min-motion", a->min_motion_px,
                  "A held key counts when the replay moves the gripper this many pixels (at 64x64)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--min-scene-share", a->min_scene_share,
                  "A frame keeps the scene when this share of the pixels the replay leaves as at its start "
                  "are within 24 grey levels of the replay")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  cmd->add_option("--video", a->video,
                  "Write the stream beside the DojoSim replay, with keypoints, to this mp4");
  cmd->add_option("--out", a->json_out, "Write the scores as JSON to this file");
  add_json_option(cmd, a->json);
  cmd->callback([a] { set_action([a] { return run_serve_check(*a); }); });
}

}  // namespace dojo::cli
