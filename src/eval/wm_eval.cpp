#include "eval/wm_eval.h"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <functional>
#include <optional>

#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "core/progress.h"
#include "core/safetensors.h"
#include "data/clip_loader.h"
#include "data/episode_source.h"
#include "data/multi_view.h"
#include "eval/keypoint_metrics.h"
#include "eval/lpips.h"
#include "eval/metrics.h"
#include "io/video.h"

namespace fs = std::filesystem;

namespace dojo::eval {

nlohmann::json SourceScore::to_json() const {
  nlohmann::json j = {{"psnr", psnr},
                      {"ssim", ssim},
                      {"psnr_all_frames", psnr_all_frames},
                      {"ssim_all_frames", ssim_all_frames}};
  if (!std::isnan(lpips)) j["lpips"] = lpips;
  if (!std::isnan(keypoint_error)) j["keypoint_error_px"] = keypoint_error;
  if (!std::isnan(detection)) j["detection"] = detection;
  if (!std::isnan(presence)) j["presence"] = presence;
  return j;
}

nlohmann::json WmEvalResult::to_json() const {
  nlohmann::json per = nlohmann::json::array();
  for (const auto& v : videos) {
    nlohmann::json j = {{"episode", v.episode}};
    for (const auto& [name, s] : v.sources) j[name] = s.to_json();
    for (const auto& [camera, sources] : v.views)
      for (const auto& [name, s] : sources) j["views"][camera][name] = s.to_json();
    if (!v.video.empty()) j["video"] = v.video;
    per.push_back(j);
  }
  nlohmann::json out = {{"dataset", dataset},
                        {"split", split},
                        {"data", data},
                        {"videos", static_cast<int>(videos.size())},
                        {"frames_per_video", frames},
                        {"scored_frames",
                         "predicted frames (1 .. frames_per_video - 1); *_all_frames: "
                         "frame 0 included, as the released protocol"},
                        {"detection_radius_px", detection_radius},
                        {"seconds", seconds},
                        {"frames_per_second", frames_per_second},
                        {"tokenizer_psnr_by_latent", tokenizer_psnr_by_latent},
                        {"per_video", per}};
  nlohmann::json curves = nlohmann::json::object();
  for (const auto& [name, s] : sources) {
    out[name] = s.to_json();
    curves[name] = {{"psnr", s.psnr_per_frame}};
    if (!s.keypoint_error_per_frame.empty()) {
      auto numbers = [](const std::vector<double>& values) {
        nlohmann::json a = nlohmann::json::array();
        for (double v : values) a.push_back(finite_or_null(v));
        return a;
      };
      curves[name]["keypoint_error_px"] = numbers(s.keypoint_error_per_frame);
      curves[name]["detection"] = numbers(s.detection_per_frame);
      curves[name]["presence"] = numbers(s.presence_per_frame);
    }
  }
  out["per_frame"] = curves;
  for (const auto& [camera, view_sources] : views)
    for (const auto& [name, s] : view_sources) out["views"][camera][name] = s.to_json();
  // The world model's scores also at the top level, as before the per-source layout.
  out["psnr"] = model().psnr;
  out["ssim"] = model().ssim;
  return out;
}

torch::Tensor read_rollout_actions(const fs::path& file) {
  const auto actions = SafetensorsFile::open(file).tensor("actions", true).to(torch::kFloat);
  DOJO_CHECK(actions.dim() == 2 && actions.size(1) == 384 && actions.size(0) % 12 == 0 && actions.size(0) > 0,
             file.string() + ": tensor 'actions' must be [12 K, 384], got " + shape_string(actions.sizes()));
  return actions;
}

namespace {

// What the keypoint scores of one video need besides its frames.
struct KeypointTruth {
  models::KeypointProbe* probe = nullptr;
  int64_t offset = 0;
  torch::Tensor truth;  // [T, 3, 3]
};

// The mean of values[1 ..]: the predicted frames.
double mean_after_frame_0(const std::vector<double>& values) {
  return nan_mean(std::vector<double>(values.begin() + std::min<size_t>(1, values.size()), values.end()));
}

// One video from one source against the ground truth [T, H, W, 3]: scores on frames 1 .. T-1
// (frame 0 is given, not predicted), the released protocol's PSNR / SSIM over all T beside them.
SourceScore score_video(const torch::Tensor& video, const torch::Tensor& gt, const Lpips* lpips,
                        const KeypointTruth& kp) {
  DOJO_CHECK(video.size(0) >= 2, "eval: a video needs a predicted frame after frame 0");
  SourceScore s;
  const auto psnr = psnr_per_frame(video, gt).to(torch::kFloat64).contiguous();  // [T]
  s.psnr_per_frame.assign(psnr.data_ptr<double>(), psnr.data_ptr<double>() + psnr.numel());
  const int64_t T = video.size(0);
  const auto m = video_metrics(video.narrow(0, 1, T - 1), gt.narrow(0, 1, T - 1), lpips);
  s.psnr = m.psnr;
  s.ssim = m.ssim;
  s.lpips = m.lpips;
  // The released protocol's means over all T frames: frame 0's values joined to the predicted ones'.
  const double frame0_ssim = ssim_per_frame(video.narrow(0, 0, 1), gt.narrow(0, 0, 1)).item<double>();
  s.psnr_all_frames = (s.psnr_per_frame[0] + m.psnr * static_cast<double>(T - 1)) / static_cast<double>(T);
  s.ssim_all_frames = (frame0_ssim + m.ssim * static_cast<double>(T - 1)) / static_cast<double>(T);
  if (kp.probe != nullptr && kp.truth.defined()) {
    const auto scores = score_keypoints(models::detect_keypoints(*kp.probe, video), kp.offset, kp.truth,
                                        video.size(1), video.size(2));
    s.keypoint_error_per_frame = scores.error;
    s.detection_per_frame = scores.detected;
    s.presence_per_frame = scores.present;
    s.keypoint_error = mean_after_frame_0(scores.error);
    s.detection = mean_after_frame_0(scores.detected);
    s.presence = mean_after_frame_0(scores.present);
  }
  return s;
}

// Means over videos, and per frame index over the videos that have a value there.
SourceScore mean_over_videos(const std::vector<const SourceScore*>& videos) {
  SourceScore out;
  const double n = static_cast<double>(videos.size());
  std::vector<double> errors, detections, presences, lpips;
  for (const auto* v : videos) {
    out.psnr += v->psnr / n;
    out.ssim += v->ssim / n;
    out.psnr_all_frames += v->psnr_all_frames / n;
    out.ssim_all_frames += v->ssim_all_frames / n;
    lpips.push_back(v->lpips);
    errors.push_back(v->keypoint_error);
    detections.push_back(v->detection);
    presences.push_back(v->presence);
  }
  bool all_lpips = true;
  for (double v : lpips) all_lpips = all_lpips && !std::isnan(v);
  if (all_lpips) out.lpips = nan_mean(lpips);
  out.keypoint_error = nan_mean(errors);
  out.detection = nan_mean(detections);
  out.presence = nan_mean(presences);
  auto per_frame = [&](std::vector<double> SourceScore::*field) {
    std::vector<double> mean;
    for (size_t t = 0; t < (videos.front()->*field).size(); ++t) {
      std::vector<double> at_t;
      for (const auto* v : videos) at_t.push_back((v->*field)[t]);
      mean.push_back(nan_mean(at_t));
    }
    return mean;
  };
  out.psnr_per_frame = per_frame(&SourceScore::psnr_per_frame);
  out.keypoint_error_per_frame = per_frame(&SourceScore::keypoint_error_per_frame);
  out.detection_per_frame = per_frame(&SourceScore::detection_per_frame);
  out.presence_per_frame = per_frame(&SourceScore::presence_per_frame);
  return out;
}

// A panel of the side-by-side video: enlarged, with keypoints drawn (the simulator's on the
// ground truth, the probe's elsewhere).
torch::Tensor video_panel(const torch::Tensor& video, const WmEvalOptions& o, const KeypointTruth& kp,
                          bool ground_truth) {
  auto panel = io::upscale_nearest(video, o.video_scale).clone();  // [T, sH, sW, 3]
  static const std::vector<std::array<uint8_t, 3>> kColors = {{255, 60, 60}, {60, 220, 60}, {70, 140, 255}};
  if (kp.truth.defined() && (ground_truth || kp.probe != nullptr)) {
    torch::Tensor points, show;
    if (ground_truth) {
      points = kp.truth.narrow(2, 0, 2);
      show = kp.truth.select(2, 2).gt(0.5);
    } else {
      const auto out = models::detect_keypoints(*kp.probe, video);
      points = out.coords.narrow(1, kp.offset, 3);
      show = out.presence.narrow(1, kp.offset, 3).gt(0);
    }
    io::draw_markers(panel, points, show, std::max<int64_t>(1, o.video_scale), kColors);
  }
  return panel;
}

}  // namespace

WmEvalResult evaluate_world_model(infer::WorldModel& model, const fs::path& dataset, const std::string& split,
                                  const WmEvalOptions& o) {
  DOJO_CHECK(o.chunks > 0, "eval: --chunks must be positive");
  DOJO_CHECK(o.video_scale >= 1, "eval: the video scale must be >= 1");
  const data::RolloutData rollout_data(
      dataset, o.chunks, data::parse_action_ranges(model.action_ranges(), "world model actions"), o.data);
  const auto& info = rollout_data.source().info();
  const auto& clip = rollout_data.clip();
  auto episodes = rollout_data.episodes(split);
  DOJO_CHECK(!episodes.empty(), dataset.string() + ": no episode of split '" + split +
                                    "' is long enough for " + std::to_string(clip.num_frames) +
                                    " frames at frame stride " + std::to_string(rollout_data.stride()));
  LOG_INFO("eval: ", rollout_data.describe());
  if (o.max_episodes > 0 && static_cast<int>(episodes.size()) > o.max_episodes)
    episodes.resize(o.max_episodes);
  DOJO_CHECK(!o.action_sensitivity || episodes.size() >= 2,
             "eval: action sensitivity shuffles actions between episodes and needs at least 2");
  if (!o.video_dir.empty()) fs::create_directories(o.video_dir);
  const int64_t offset = o.probe != nullptr
                             ? models::keypoint_offset((*o.probe)->config(), data::to_string(info.embodiment))
                             : 0;

  // Several cameras in one canvas: each is scored on its own part too; simulator keypoints belong
  // to the main camera, so they score that part alone.
  const auto* tiled = dynamic_cast<const data::MultiViewSource*>(&rollout_data.source());
  const data::ViewTiling* tiling = tiled != nullptr ? &tiled->tiling() : nullptr;

  std::vector<data::EpisodeClip> clips;
  for (size_t ep : episodes) clips.push_back(rollout_data.read(ep));
  if (o.probe != nullptr && !clips.front().keypoints.defined())
    LOG_WARN("eval: ", dataset.string(), " has no simulator keypoints; keypoint scores are left out");
  const size_t n = clips.size();

  WmEvalResult r;
  r.dataset = dataset.string();
  r.split = split;
  r.data = rollout_data.describe();
  r.frames = clip.num_frames;
  r.detection_radius = detection_radius_px(info.height, info.width);
  const int runs = o.action_sensitivity ? 3 : 1;
  Progress progress("eval " + split, static_cast<int64_t>(n) * o.chunks * runs, "chunk");
  double rollout_seconds = 0;
  for (size_t b = 0; b < n; b += static_cast<size_t>(o.batch)) {
    const size_t e = std::min(n, b + static_cast<size_t>(o.batch));
    std::vector<at::Tensor> videos, actions, shuffled;
    for (size_t i = b; i < e; ++i) {
      videos.push_back(clips[i].video);
      actions.push_back(clips[i].actions);
      shuffled.push_back(clips[(i + 1) % n].actions);  // another episode's actions
    }
    const auto gt = torch::stack(videos);  // [n, 1 + 12K, H, W, 3]
    const auto first = gt.select(1, 0).contiguous();
    auto roll = [&](const torch::Tensor& a) {
      if (o.student != nullptr)
        return o.student->rollout(first, a, o.seed, [&](int64_t step) {
          if ((step + 1) % 3 == 0) progress.advance(static_cast<int64_t>(e - b));  // 3 steps a chunk
        });
      return model.rollout(first, a, o.seed, o.sampler, o.concat,
                           [&](int64_t) { progress.advance(static_cast<int64_t>(e - b)); });
    };
    const auto t0 = std::chrono::steady_clock::now();
    const auto pred = roll(torch::stack(actions));  // [n, 1 + 12K, H, W, 3]
    rollout_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::map<std::string, torch::Tensor> rollouts = {{"world_model", pred},
                                                     {"tokenizer", model.reconstruct_chunks(gt, o.concat)}};
    if (o.action_sensitivity) {
      rollouts["shuffled_actions"] = roll(torch::stack(shuffled));
      rollouts["zero_actions"] = roll(torch::zeros_like(torch::stack(actions)));
    }
    for (size_t i = b; i < e; ++i) {
      const int64_t k = static_cast<int64_t>(i - b);
      const KeypointTruth kp = tiling == nullptr ? KeypointTruth{o.probe, offset, clips[i].keypoints}
                                                 : KeypointTruth{};  // the canvas: no keypoints
      VideoScore s;
      s.episode = info.episodes[episodes[i]].id;
      const auto copy = gt[k].select(0, 0).unsqueeze(0).expand_as(gt[k]).contiguous();
      // Every source on frames [T, H, W, 3] cut by `cut` (the whole canvas, or one view of it).
      auto score_all = [&](const std::function<torch::Tensor(const torch::Tensor&)>& cut,
                           const KeypointTruth& truth, std::map<std::string, SourceScore>& out) {
        const auto target = cut(gt[k]);
        for (const auto& [name, video] : rollouts)
          out[name] = score_video(cut(video[k]), target, name == "tokenizer" ? nullptr : o.lpips, truth);
        out["copy_frame"] = score_video(cut(copy), target, o.lpips, truth);
        if (o.probe != nullptr && truth.truth.defined())
          out["ground_truth"] = score_video(target, target, nullptr, truth);
      };
      score_all([](const torch::Tensor& v) { return v; }, kp, s.sources);
      if (tiling != nullptr)
        for (int v = 0; v < tiling->count(); ++v)
          score_all([&](const torch::Tensor& frames) { return tiling->crop(frames, v, 1, 2).contiguous(); },
                    v == 0 ? KeypointTruth{o.probe, offset, clips[i].keypoints} : KeypointTruth{},
                    s.views[tiling->cameras[v]]);
      if (!o.video_dir.empty() && static_cast<int>(r.videos.size()) < o.videos) {
        s.video = (o.video_dir / (split + "_" + s.episode + ".mp4")).string();
        io::write_comparison_video(
            s.video,
            {video_panel(gt[k], o, kp, true), video_panel(pred[k], o, kp, false),
             video_panel(copy, o, kp, false), video_panel(rollouts["tokenizer"][k], o, kp, false)},
            {"ground truth", "world model", "copy frame 0", "tokenizer"}, clips[i].fps);
      }
      r.videos.push_back(std::move(s));
    }
  }
  progress.finish();
  for (const auto& [name, unused] : r.videos.front().sources) {
    std::vector<const SourceScore*> per_video;
    for (const auto& v : r.videos) per_video.push_back(&v.sources.at(name));
    r.sources[name] = mean_over_videos(per_video);
  }
  for (const auto& [camera, view_sources] : r.videos.front().views)
    for (const auto& [name, unused] : view_sources) {
      std::vector<const SourceScore*> per_video;
      for (const auto& v : r.videos) per_video.push_back(&v.views.at(camera).at(name));
      r.views[camera][name] = mean_over_videos(per_video);
    }
  // Tokenizer PSNR by latent index within a chunk: frame 0 alone, then 4 frames per latent.
  const auto& tok = r.tokenizer().psnr_per_frame;
  r.tokenizer_psnr_by_latent.assign(4, 0.0);
  std::vector<int> counts(4, 0);
  for (size_t f = 0; f < tok.size(); ++f) {
    const size_t latent = f == 0 ? 0 : (f - 1) % 12 / 4 + 1;
    r.tokenizer_psnr_by_latent[latent] += tok[f];
    ++counts[latent];
  }
  for (size_t l = 0; l < 4; ++l) r.tokenizer_psnr_by_latent[l] /= std::max(1, counts[l]);
  r.seconds = rollout_seconds;
  r.frames_per_second = rollout_seconds > 0 ? static_cast<double>(n) * (r.frames - 1) / rollout_seconds : 0;
  return r;
}

std::string markdown_table(const std::vector<WmEvalResult>& results) {
  if (results.empty()) return "";
  const bool with_lpips = !std::isnan(results[0].model().lpips);
  const bool with_keypoints = !std::isnan(results[0].model().keypoint_error);
  const bool with_sensitivity = results[0].sources.count("shuffled_actions") > 0;
  auto fmt = [](double v, int digits = 2) {
    if (std::isnan(v)) return std::string("-");
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.*f", digits, v);
    return std::string(buf);
  };
  std::string s = "| split | videos | PSNR | SSIM |";
  std::string rule = "|---|---|---|---|";
  if (with_lpips) s += " LPIPS |", rule += "---|";
  s += " copy-frame PSNR | copy-frame SSIM |";
  rule += "---|---|";
  if (with_lpips) s += " copy-frame LPIPS |", rule += "---|";
  s += " tokenizer PSNR | released protocol (frame 0 included) PSNR: model / copy-frame |";
  rule += "---|---|";
  s = "Scores on the predicted frames (frame 0, which every method is given, excluded); the released "
      "protocol's PSNR with frame 0 beside them.\n\n" +
      s + "\n" + rule + "\n";
  for (const auto& r : results) {
    s += "| " + r.split + " | " + std::to_string(r.videos.size()) + " | " + fmt(r.model().psnr, 3) + " | " +
         fmt(r.model().ssim, 3) + " |";
    if (with_lpips) s += " " + fmt(r.model().lpips, 3) + " |";
    s += " " + fmt(r.copy_frame().psnr, 3) + " | " + fmt(r.copy_frame().ssim, 3) + " |";
    if (with_lpips) s += " " + fmt(r.copy_frame().lpips, 3) + " |";
    s += " " + fmt(r.tokenizer().psnr, 3) + " | " + fmt(r.model().psnr_all_frames, 3) + " / " +
         fmt(r.copy_frame().psnr_all_frames, 3) + " |\n";
  }
  if (with_keypoints) {
    s += "\nKeypoint error (pixels) and detection rate of the probe (keypoints found within " +
         fmt(results[0].detection_radius, 1) +
         " px of the truth):\n\n"
         "| split | world model | copy frame | tokenizer | ground truth | detection: world model | "
         "detection: ground truth |\n|---|---|---|---|---|---|---|\n";
    for (const auto& r : results) {
      const auto gt = r.sources.count("ground_truth") ? r.sources.at("ground_truth") : SourceScore{};
      s += "| " + r.split + " | " + fmt(r.model().keypoint_error) + " | " +
           fmt(r.copy_frame().keypoint_error) + " | " + fmt(r.tokenizer().keypoint_error) + " | " +
           fmt(gt.keypoint_error) + " | " + fmt(r.model().detection, 3) + " | " + fmt(gt.detection, 3) +
           " |\n";
    }
  }
  if (with_sensitivity) {
    s += "\nAction sensitivity (the same rollouts driven by other actions):\n\n"
         "| split | PSNR: true | shuffled | zero | keypoint error: true | shuffled | zero |\n"
         "|---|---|---|---|---|---|---|\n";
    for (const auto& r : results) {
      const auto& sh = r.sources.at("shuffled_actions");
      const auto& z = r.sources.at("zero_actions");
      s += "| " + r.split + " | " + fmt(r.model().psnr) + " | " + fmt(sh.psnr) + " | " + fmt(z.psnr) + " | " +
           fmt(r.model().keypoint_error) + " | " + fmt(sh.keypoint_error) + " | " + fmt(z.keypoint_error) +
           " |\n";
    }
  }
  if (!results[0].views.empty()) {
    s += "\nPer camera (each camera's part of the multi-view canvas; keypoints on the main camera's):\n\n"
         "| split | camera | PSNR: world model | copy frame | tokenizer | keypoint error: world model | copy "
         "frame |\n|---|---|---|---|---|---|---|\n";
    for (const auto& r : results)
      for (const auto& [camera, v] : r.views)
        s += "| " + r.split + " | " + camera + " | " + fmt(v.at("world_model").psnr) + " | " +
             fmt(v.at("copy_frame").psnr) + " | " + fmt(v.at("tokenizer").psnr) + " | " +
             fmt(v.at("world_model").keypoint_error) + " | " + fmt(v.at("copy_frame").keypoint_error) +
             " |\n";
  }
  return s;
}

}  // namespace dojo::eval
