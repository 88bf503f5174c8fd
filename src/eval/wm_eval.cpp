#include "eval/wm_eval.h"

#include <algorithm>
#include <chrono>
#include <cstdio>

#include "core/error.h"
#include "core/log.h"
#include "core/progress.h"
#include "core/safetensors.h"
#include "data/clip_loader.h"
#include "data/episode_source.h"
#include "data/episode_store.h"
#include "eval/lpips.h"
#include "eval/metrics.h"
#include "io/video.h"

namespace fs = std::filesystem;

namespace dojo::eval {

nlohmann::json WmEvalResult::to_json() const {
  nlohmann::json per = nlohmann::json::array();
  for (const auto& v : videos) {
    nlohmann::json j = {
        {"episode", v.episode},          {"psnr", v.psnr},           {"ssim", v.ssim},
        {"copy_psnr", v.copy_psnr},      {"copy_ssim", v.copy_ssim}, {"tokenizer_psnr", v.recon_psnr},
        {"tokenizer_ssim", v.recon_ssim}};
    if (!std::isnan(v.lpips)) j["lpips"] = v.lpips, j["copy_lpips"] = v.copy_lpips;
    if (!v.video.empty()) j["video"] = v.video;
    per.push_back(j);
  }
  nlohmann::json out = {{"dataset", dataset},
                        {"split", split},
                        {"videos", static_cast<int>(videos.size())},
                        {"frames_per_video", frames},
                        {"psnr", psnr},
                        {"ssim", ssim},
                        {"copy_first_frame", {{"psnr", copy_psnr}, {"ssim", copy_ssim}}},
                        {"tokenizer_round_trip", {{"psnr", recon_psnr}, {"ssim", recon_ssim}}},
                        {"seconds", seconds},
                        {"frames_per_second", frames_per_second},
                        {"per_video", per}};
  if (!std::isnan(lpips)) {
    out["lpips"] = lpips;
    out["copy_first_frame"]["lpips"] = copy_lpips;
  }
  return out;
}

EpisodeClip read_episode_clip(const fs::path& dataset, const std::string& split, const std::string& episode,
                              int chunks) {
  DOJO_CHECK(chunks > 0, "rollout: --chunks must be positive");
  const auto source = data::open_dataset(dataset);
  const auto& info = source->info();
  const auto indices = source->split_indices(split);
  DOJO_CHECK(!indices.empty(), dataset.string() + ": no episodes in split '" + split + "'");
  size_t ep = indices.front();
  if (!episode.empty()) {
    const auto it = std::find_if(info.episodes.begin(), info.episodes.end(),
                                 [&](const data::EpisodeEntry& e) { return e.id == episode; });
    DOJO_CHECK(it != info.episodes.end(), dataset.string() + ": no episode '" + episode + "'");
    ep = static_cast<size_t>(it - info.episodes.begin());
  }
  data::ClipConfig clip;
  clip.num_frames = 1 + 12 * chunks;
  clip.strides = {1};
  clip.height = info.height;
  clip.width = info.width;
  EpisodeClip out;
  out.episode = info.episodes[ep].id;
  out.fps = info.fps;
  DOJO_CHECK(data::window_fits(info.episodes[ep].frames, 1, clip.num_frames),
             dataset.string() + ": episode " + out.episode + " is shorter than " +
                 std::to_string(clip.num_frames) + " frames");
  const auto c = data::ClipDataset(source, clip, "all").read(ep, data::make_window(0, 1, clip.num_frames));
  out.video = c.video;
  out.actions = c.actions;
  return out;
}

torch::Tensor read_rollout_actions(const fs::path& file) {
  const auto actions = SafetensorsFile::open(file).tensor("actions", true).to(torch::kFloat);
  DOJO_CHECK(actions.dim() == 2 && actions.size(1) == 384 && actions.size(0) % 12 == 0 && actions.size(0) > 0,
             file.string() + ": tensor 'actions' must be [12 K, 384], got " + shape_string(actions.sizes()));
  return actions;
}

WmEvalResult evaluate_world_model(infer::WorldModel& model, const fs::path& dataset, const std::string& split,
                                  const WmEvalOptions& o) {
  DOJO_CHECK(o.chunks > 0, "eval: --chunks must be positive");
  const auto source = data::open_dataset(dataset);
  const auto& info = source->info();
  data::ClipConfig clip;
  clip.num_frames = 1 + 12 * o.chunks;
  clip.strides = {1};
  clip.height = info.height;
  clip.width = info.width;
  data::ClipDataset ds(source, clip, split);
  std::vector<size_t> episodes;
  for (size_t ep : ds.episodes())
    if (data::window_fits(info.episodes[ep].frames, 1, clip.num_frames)) episodes.push_back(ep);
  DOJO_CHECK(!episodes.empty(), dataset.string() + ": no episode of split '" + split +
                                    "' is long enough for " + std::to_string(clip.num_frames) + " frames");
  if (o.max_episodes > 0 && static_cast<int>(episodes.size()) > o.max_episodes)
    episodes.resize(o.max_episodes);
  if (!o.video_dir.empty()) fs::create_directories(o.video_dir);

  WmEvalResult r;
  r.dataset = dataset.string();
  r.split = split;
  r.frames = clip.num_frames;
  Progress progress("eval " + split, static_cast<int64_t>(episodes.size()) * o.chunks, "chunk");
  double rollout_seconds = 0;
  for (size_t b = 0; b < episodes.size(); b += static_cast<size_t>(o.batch)) {
    const size_t e = std::min(episodes.size(), b + static_cast<size_t>(o.batch));
    std::vector<at::Tensor> gt_videos, gt_actions;
    for (size_t i = b; i < e; ++i) {
      const auto c = ds.read(episodes[i], data::make_window(0, 1, clip.num_frames));
      gt_videos.push_back(c.video);
      gt_actions.push_back(c.actions);
    }
    const auto gt = torch::stack(gt_videos);  // [n, 1 + 12K, H, W, 3]
    const auto t0 = std::chrono::steady_clock::now();
    const auto pred =
        model.rollout(gt.select(1, 0).contiguous(), torch::stack(gt_actions), o.seed, o.sampler, o.concat,
                      [&](int64_t) { progress.advance(static_cast<int64_t>(e - b)); });
    rollout_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const auto recon = model.reconstruct_chunks(gt, o.concat);  // [n, 1 + 12K, H, W, 3]
    for (size_t i = b; i < e; ++i) {
      const int64_t k = static_cast<int64_t>(i - b);
      VideoScore s;
      s.episode = info.episodes[episodes[i]].id;
      const auto m = video_metrics(pred[k], gt[k], o.lpips);
      const auto copy = gt[k].select(0, 0).unsqueeze(0).expand_as(gt[k]).contiguous();
      const auto mc = video_metrics(copy, gt[k], o.lpips);
      const auto mr = video_metrics(recon[k], gt[k], nullptr);
      s.recon_psnr = mr.psnr;
      s.recon_ssim = mr.ssim;
      s.lpips = m.lpips;
      s.copy_lpips = mc.lpips;
      s.psnr = m.psnr;
      s.ssim = m.ssim;
      s.copy_psnr = mc.psnr;
      s.copy_ssim = mc.ssim;
      if (!o.video_dir.empty() && static_cast<int>(r.videos.size()) < o.videos) {
        s.video = (o.video_dir / (split + "_" + s.episode + ".mp4")).string();
        io::write_comparison_video(s.video, {gt[k], pred[k], copy, recon[k]},
                                   {"ground truth", "world model", "copy frame 0", "tokenizer"}, info.fps);
      }
      r.videos.push_back(s);
    }
  }
  progress.finish();
  for (const auto& v : r.videos) {
    r.psnr += v.psnr;
    r.ssim += v.ssim;
    r.copy_psnr += v.copy_psnr;
    r.copy_ssim += v.copy_ssim;
    r.recon_psnr += v.recon_psnr;
    r.recon_ssim += v.recon_ssim;
  }
  const double n = static_cast<double>(r.videos.size());
  if (o.lpips) {
    r.lpips = r.copy_lpips = 0;
    for (const auto& v : r.videos) r.lpips += v.lpips / n, r.copy_lpips += v.copy_lpips / n;
  }
  r.psnr /= n;
  r.ssim /= n;
  r.copy_psnr /= n;
  r.copy_ssim /= n;
  r.recon_psnr /= n;
  r.recon_ssim /= n;
  r.seconds = rollout_seconds;
  r.frames_per_second = rollout_seconds > 0 ? n * (r.frames - 1) / rollout_seconds : 0;
  return r;
}

std::string markdown_table(const std::vector<WmEvalResult>& results) {
  const bool with_lpips = !results.empty() && !std::isnan(results[0].lpips);
  std::string s = "| split | videos | PSNR | SSIM |";
  s += with_lpips ? " LPIPS |" : "";
  s += " copy-frame PSNR | copy-frame SSIM |";
  s += with_lpips ? " copy-frame LPIPS |" : "";
  s += " tokenizer round-trip PSNR |";
  s += with_lpips ? "\n|---|---|---|---|---|---|---|---|---|\n" : "\n|---|---|---|---|---|---|---|\n";
  char line[320];
  for (const auto& r : results) {
    if (with_lpips)
      std::snprintf(line, sizeof line, "| %s | %zu | %.3f | %.3f | %.3f | %.3f | %.3f | %.3f | %.3f |\n",
                    r.split.c_str(), r.videos.size(), r.psnr, r.ssim, r.lpips, r.copy_psnr, r.copy_ssim,
                    r.copy_lpips, r.recon_psnr);
    else
      std::snprintf(line, sizeof line, "| %s | %zu | %.3f | %.3f | %.3f | %.3f | %.3f |\n", r.split.c_str(),
                    r.videos.size(), r.psnr, r.ssim, r.copy_psnr, r.copy_ssim, r.recon_psnr);
    s += line;
  }
  return s;
}

}  // namespace dojo::eval
