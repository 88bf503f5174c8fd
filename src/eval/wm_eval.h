// The paper's teacher evaluation on a dataset split: for each episode, the first ground-truth
// frame and the episode's actions drive a rollout of 1 + 12 K frames (K = 4 chunks: 49 frames,
// 3 autoregressive resets); PSNR and SSIM are taken per frame, averaged per video, then over
// videos. References are scored the same way:
//   copy_frame         the real conditioning frame repeated: what ignoring the actions gets for free
//   tokenizer          the tokenizer round trip of the ground truth, chunked as the rollout is: the
//                      ceiling for a rollout decoded by this tokenizer (every latent predicted right)
//   shuffled_actions   the same rollout driven by another episode's actions, and
//   zero_actions       by all-zero (hold still) actions: with the true-action rollout these three
//                      measure whether the model uses the actions at all (action sensitivity)
// Every score is taken on the predicted frames only (1 .. 12 K), for every source: frame 0 is
// given, and copy-frame's frame 0 is the ground truth itself (PSNR capped at 80 dB), which would
// lift its mean by ~1 dB over 49 frames. The released protocol includes frame 0; its PSNR and SSIM
// are kept beside (psnr_all_frames, ssim_all_frames), and the per-frame curves keep frame 0.
// With a keypoint probe, every source also gets the keypoint error (pixels between the probe's
// keypoints on its frames and the simulator's ground truth of the same step) and the detection
// rate (share of the ground truth's in-view keypoints the probe places within
// detection_radius_px of the truth: 3 px at 64x64; "presence" is the share it merely says are
// there); the probe on the ground truth frames themselves is the "ground_truth" source, the floor
// of both.
#pragma once

#include <cmath>
#include <cstdint>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "data/episode_clip.h"
#include "infer/streaming.h"
#include "infer/world_model.h"
#include "models/keypoint_probe.h"

namespace dojo::eval {

class Lpips;

struct WmEvalOptions {
  int chunks = 4;                 // 4 x 12 actions: the paper's 49-frame protocol
  data::RolloutDataOptions data;  // robot, frame stride, action normalisation, frame size
  int max_episodes = 16;          // evaluate at most this many episodes of the split (0: all)
  int batch = 4;                  // episodes rolled out together
  infer::SamplerOptions sampler;
  infer::ConcatMode concat = infer::ConcatMode::kAligned;
  uint64_t seed = 0;
  std::filesystem::path video_dir;         // side-by-side videos (ground truth | prediction | ...) when set
  int videos = 4;                          // how many episodes get a video
  int video_scale = 4;                     // videos enlarged this many times, nearest neighbour
  const Lpips* lpips = nullptr;            // LPIPS as well, when the user supplied its weights
  models::KeypointProbe* probe = nullptr;  // keypoint error and detection rate, when given
  // Also roll out with shuffled and with zero actions (3x the rollouts).
  bool action_sensitivity = false;
  // Roll out by streaming this student (one latent frame per step) instead of the teacher's
  // chunked sampler; the tokenizer and action ranges still come from the model passed in.
  infer::StreamingEngine* student = nullptr;
};

// One source's scores on a split: per-video means (each the mean over its frames), then the
// mean over videos; per-frame means over videos for plotting.
struct SourceScore {
  double psnr = 0, ssim = 0;                        // predicted frames (1 ..)
  double psnr_all_frames = 0, ssim_all_frames = 0;  // the released protocol: frame 0 included
  double lpips = std::nan("");
  double keypoint_error = std::nan("");  // pixels at the frame size
  double detection = std::nan("");       // share of in-view ground-truth keypoints found in the radius
  double presence = std::nan("");        // share said present, wherever the probe put them
  // Every frame, frame 0 included.
  std::vector<double> psnr_per_frame, keypoint_error_per_frame, detection_per_frame, presence_per_frame;
  nlohmann::json to_json() const;
};

struct VideoScore {
  std::string episode;
  std::map<std::string, SourceScore> sources;  // per-frame vectors hold this video's frames
  // A multi-view canvas: every source scored on each camera's part of it (keypoints on the main
  // camera's, where its simulator keypoints lie), by camera.
  std::map<std::string, std::map<std::string, SourceScore>> views;
  std::string video;  // side-by-side file, when written
};

struct WmEvalResult {
  std::string dataset, split;
  std::string data;  // how the dataset was read (data::RolloutData::describe())
  std::vector<VideoScore> videos;
  std::map<std::string, SourceScore> sources;  // world_model, copy_frame, tokenizer, ...
  // Multi-view: the sources' scores on each camera's part of the canvas (means over videos), by
  // camera; `sources` then scores the whole canvas, without keypoints.
  std::map<std::string, std::map<std::string, SourceScore>> views;
  // Tokenizer round-trip PSNR by a frame's latent index within its chunk: [0] the conditioning
  // frame, [i] frames 4(i-1)+1 .. 4i of each chunk. Later latents merge more motion.
  std::vector<double> tokenizer_psnr_by_latent;
  int frames = 0;                             // per video
  double detection_radius = 0;                // pixels at the frame size
  double seconds = 0, frames_per_second = 0;  // generated frames / rollout time (true actions)
  const SourceScore& model() const { return sources.at("world_model"); }
  const SourceScore& copy_frame() const { return sources.at("copy_frame"); }
  const SourceScore& tokenizer() const { return sources.at("tokenizer"); }
  nlohmann::json to_json() const;
};

// Actions from a safetensors file holding "actions" [12 K, 384] (counterfactual rollouts).
torch::Tensor read_rollout_actions(const std::filesystem::path& file);

WmEvalResult evaluate_world_model(infer::WorldModel& model, const std::filesystem::path& dataset,
                                  const std::string& split, const WmEvalOptions& options);

// Markdown tables of several results (one row per split): scores, and with keypoints or action
// sensitivity their own tables.
std::string markdown_table(const std::vector<WmEvalResult>& results);

}  // namespace dojo::eval
