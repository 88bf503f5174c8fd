// Does teleoperation hold? A session recorded by `dojo serve` from its start frame (session.json,
// video.mp4, actions.jsonl) is replayed command by command in DojoSim from the same episode's
// scene, and the keypoint probe reads the streamed frames. Two questions a frame-difference cannot
// answer: is the arm still there (the probe finds it where the replay shows it), and does it move
// the way each held key points (the gripper's image motion over the hold against the replay's).
//
// Alignment: the video is the start frame, then 4 frames per step; command row r (the recording's
// "raw" rows in order) is executed during step r of the replay and its result is frame r + 1.
#pragma once

#include <ATen/core/Tensor.h>

#include <array>
#include <cstdint>
#include <filesystem>
#include <limits>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace dojo::recipes {

struct TeleopCheckOptions {
  std::filesystem::path recording;  // a directory `dojo serve` wrote (session.json, video.mp4, actions.jsonl)
  std::filesystem::path data;       // the episodes the session started from; "" = session.json's "data"
  std::filesystem::path probe;      // keypoint probe checkpoint (models/keypoint_probe.h)
  // A held key counts when the replay moves the gripper at least this far (pixels at 64x64, scaled
  // with the frame): holds at a joint limit or along the camera's axis show no direction to agree with.
  double min_motion_px = 1.5;
  std::filesystem::path video;  // when set: the stream beside the DojoSim replay, probe marks on both
  // A streamed frame still shows the scene when at least this share of the pixels the replay leaves
  // as they were at its start (table, wall, bin, resting links) are within kSceneTolerance of the
  // replay. An arm drawn in the wrong place costs a good frame about a tenth; a stream dissolved
  // into arm-coloured bands loses most of them, while the probe alone still reads an arm into it.
  double min_scene_share = 0.75;
};

// Grey levels (mean over the channels, of 255) within which a streamed pixel matches the replay's.
constexpr double kSceneTolerance = 24;

// One key held: a run of command rows in which exactly one dimension moves, always the same way.
struct HeldKey {
  std::string dimension;  // the command's name (base_yaw, shoulder, ...)
  int sign = 0;           // +1 / -1: the direction the command moved
  int64_t first_row = 0, rows = 0;
  std::array<double, 2> replay_motion{};  // gripper keypoint displacement over the hold, pixels (u, v)
  std::array<double, 2> stream_motion{};  // the same, read by the probe from the streamed frames
  // Both ends of the hold keep the scene and the probe finds the gripper there (in a dissolved
  // frame the probe's gripper is noise, and so would be its motion).
  bool stream_found = false;
  bool counted = false;  // the replay's motion is at least min_motion_px
  bool agrees = false;   // counted, found, and the stream moved >= min_motion_px / 2 along the replay's way
};

struct TeleopCheck {
  std::string episode;
  int64_t frames = 0;  // streamed frames, the start frame included
  double seconds = 0;  // at the session's frame rate
  // Share of frames that still show the scene (min_scene_share) and where the probe finds the
  // arm (>= 2 of its 3 keypoints). Every arm_found figure below counts kept-scene frames only.
  double arm_found = 0;
  double arm_found_by_probe_alone = 0;  // the probe's reading whatever the frame has become
  double scene_kept = 0, scene_kept_first_100 = 0, scene_kept_last_100 = 0;
  std::vector<double> scene_share;  // per frame: share of the replay's unchanged pixels the stream keeps
  double arm_in_view = 0;           // share of frames where the replay has >= 2 arm keypoints in view
  double arm_found_where_in_view = 0;
  // The probe on DojoSim's own frames of the same commands, where they show the arm: its ceiling.
  double arm_found_in_replay = 0;
  double arm_found_first_100 = 0, arm_found_last_100 = 0;  // over the first / last 100 frames
  std::vector<int64_t> arm_lost_frames;  // frames where the replay shows the arm and the probe finds none
  double keypoint_error_px = std::numeric_limits<double>::quiet_NaN();  // stream vs replay, mean
  double detected = std::numeric_limits<double>::quiet_NaN();  // replay's keypoints found within the radius
  std::vector<HeldKey> keys;
  int64_t counted_keys = 0, agreeing_keys = 0;
  double sign_agreement = std::numeric_limits<double>::quiet_NaN();  // agreeing / counted

  nlohmann::json to_json() const;
};

// Per frame, the share of the pixels where the replay still equals its own frame 0 (every channel
// within 12) that the stream shows within kSceneTolerance of the replay: what a stream must keep of
// the scene wherever the arm is. Both [T, H, W, 3] uint8 of one size; returns [T] float64.
at::Tensor unchanged_scene_share(const at::Tensor& stream, const at::Tensor& replay);

// Throws dojo::Error naming the file for a recording that cannot be replayed: missing files, a
// recording begun after the stream's start, no raw commands, frames and commands that do not line
// up, an episode not in the data, or a replay that does not start where the episode does.
TeleopCheck check_teleop_recording(const TeleopCheckOptions& options);

}  // namespace dojo::recipes
