#include "train/latent_cache.h"

#include <optional>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/progress.h"
#include "core/safetensors.h"
#include "data/actions.h"
#include "data/clip_loader.h"
#include "data/episode_source.h"
#include "models/lam.h"
#include "models/wan_vae.h"

namespace fs = std::filesystem;

namespace dojo::train {

ActionMode parse_action_mode(const std::string& text) {
  if (text == "dataset") return ActionMode::kDataset;
  if (text == "latent") return ActionMode::kLatent;
  if (text == "none") return ActionMode::kNone;
  if (text == "ground-truth") return ActionMode::kGroundTruth;
  throw Error("unknown action mode '" + text + "' (expected dataset, latent, none or ground-truth)");
}

std::string to_string(ActionMode mode) {
  switch (mode) {
    case ActionMode::kDataset:
      return "dataset";
    case ActionMode::kLatent:
      return "latent";
    case ActionMode::kNone:
      return "none";
    case ActionMode::kGroundTruth:
      return "ground-truth";
  }
  return "?";
}

namespace {

// Ground-truth motion rows in the clip-action convention: row j (transition j -> j+1) is the
// motion at frame j+1 relative to the first frame of its 4-row chunk.
torch::Tensor chunk_relative_motion(const torch::Tensor& motion /*[T, M]*/, int chunk) {
  const int64_t rows = motion.size(0) - 1;
  auto out = torch::empty({rows, motion.size(1)});
  for (int64_t j = 0; j < rows; ++j) out[j] = motion[j + 1] - motion[(j / chunk) * chunk];
  return out;  // [T - 1, M]
}

}  // namespace

nlohmann::json LatentCacheSpec::to_json() const {
  nlohmann::json j = {
      {"dataset", fs::absolute(dataset).lexically_normal().string()},
      {"split", split},
      {"tokenizer", checkpoint_fingerprint(tokenizer)},
      {"lam", mode == ActionMode::kLatent ? checkpoint_fingerprint(lam) : nlohmann::json(nullptr)},
      {"mode", train::to_string(mode)},
      {"strides", strides},
      {"hop", hop},
      {"size", size},
      {"max_clips", max_clips},
      {"relative_actions", relative_actions},
      {"action_stats", action_stats ? action_stats->to_json() : nlohmann::json(nullptr)}};
  if (frames != 13) j["frames"] = frames;  // older caches (all 13 frames) keep their fingerprint
  if (embodiment != "auto") j["embodiment"] = embodiment;  // and caches of unnamed robots theirs
  if (!views.empty()) j["views"] = {{"cameras", views}, {"layout", view_layout}};
  return j;
}

data::OpenOptions LatentCacheSpec::open_options() const {
  data::OpenOptions o;
  o.embodiment = embodiment;
  o.views = views;
  o.view_layout = view_layout;
  return o;
}

LatentClips load_or_build_latent_clips(const LatentCacheSpec& spec, const fs::path& cache_file) {
  const auto spec_json = spec.to_json();
  if (fs::exists(cache_file)) {
    auto file = SafetensorsFile::open(cache_file);
    const auto& meta = file.metadata();
    auto it = meta.find("spec");
    if (it != meta.end() && nlohmann::json::parse(it->second) == spec_json) {
      LatentClips clips{file.tensor("latents", true), file.tensor("actions", true), spec_json};
      LOG_INFO("latent cache: ", clips.size(), " clips from ", cache_file.string());
      return clips;
    }
    LOG_INFO("latent cache: ", cache_file.string(), " was made from other data or models; rebuilding");
  }
  DOJO_CHECK(!(spec.mode == ActionMode::kLatent && spec.lam.empty()),
             "latent actions need a LAM checkpoint (--lam) for " + spec.dataset.string());

  auto vae = models::load_tokenizer(spec.tokenizer);
  vae->eval();
  std::optional<models::LatentActionModel> lam;
  if (spec.mode == ActionMode::kLatent) {
    lam = models::load_lam(spec.lam);
    DOJO_CHECK((*lam)->config.latent_dim == data::slots::kLatent.width(),
               spec.lam.string() + ": LAM latent size " + std::to_string((*lam)->config.latent_dim) +
                   " does not fill the " + std::to_string(data::slots::kLatent.width()) +
                   "-wide latent slot");
  }
  // Any format the readers know (our episodes, LeRobot, EgoDex, video folders).
  const auto source = data::open_dataset(spec.dataset, spec.open_options());
  const auto& info = source->info();
  data::ClipConfig clip;
  DOJO_CHECK(spec.frames >= 5 && (spec.frames - 1) % 4 == 0,
             "latent cache: clips need 1 + 4k frames (got " + std::to_string(spec.frames) + ")");
  clip.num_frames = spec.frames;
  clip.strides = spec.strides;
  clip.relative_actions = spec.relative_actions;
  clip.action_stats = spec.action_stats;
  clip.height = spec.size > 0 ? spec.size : info.height;
  clip.width = spec.size > 0 ? spec.size : info.width;
  DOJO_CHECK(clip.height > 0 && clip.width > 0 && clip.height % 8 == 0 && clip.width % 8 == 0,
             spec.dataset.string() + ": frame size " + std::to_string(clip.height) + "x" +
                 std::to_string(clip.width) + " is not a multiple of 8; give a --size");
  data::ClipDataset dataset(source, clip, spec.split);
  DOJO_CHECK(!dataset.episodes().empty(),
             spec.dataset.string() + ": no episodes in split '" + spec.split + "'");

  std::vector<std::pair<size_t, data::ClipWindow>> windows;
  for (size_t ep : dataset.episodes())
    for (int stride : spec.strides)
      for (auto& w : data::all_windows(info.episodes[ep].frames, stride, clip.num_frames, spec.hop))
        windows.emplace_back(ep, std::move(w));
  if (spec.max_clips > 0 && static_cast<int64_t>(windows.size()) > spec.max_clips) {
    // Evenly spaced, so every episode and stride stays represented.
    std::vector<std::pair<size_t, data::ClipWindow>> kept;
    for (int64_t i = 0; i < spec.max_clips; ++i)
      kept.push_back(windows[static_cast<size_t>(i * static_cast<int64_t>(windows.size()) / spec.max_clips)]);
    windows.swap(kept);
  }
  DOJO_CHECK(!windows.empty(), spec.dataset.string() + ": episodes are shorter than one clip");

  torch::NoGradGuard no_grad;
  std::vector<torch::Tensor> latents, actions;
  std::vector<torch::Tensor> pending_video;
  auto flush = [&] {
    if (pending_video.empty()) return;
    const auto video = models::video_to_model(torch::stack(pending_video));  // [b, 3, frames, H, W]
    latents.push_back(vae->encode_latents(video));  // [b, 16, 1 + (frames - 1) / 4, h, w]
    pending_video.clear();
  };
  Progress progress("latent cache " + spec.dataset.filename().string(), static_cast<int64_t>(windows.size()),
                    "clip");
  for (const auto& [ep, window] : windows) {
    auto c = dataset.read(ep, window);
    auto a = c.actions.clone();  // [frames - 1, 384]
    auto slot = a.slice(1, data::slots::kLatent.begin, data::slots::kLatent.end);
    switch (spec.mode) {
      case ActionMode::kDataset:
        break;
      case ActionMode::kLatent:
        slot.mul_(models::lam_encode_episode(*lam, c.video));
        break;  // mask * z
      case ActionMode::kNone:
        a.zero_();
        break;
      case ActionMode::kGroundTruth: {
        DOJO_CHECK(c.hidden_motion.defined(), spec.dataset.string() + ": episode " + info.episodes[ep].id +
                                                  " has no hidden_motion for ground-truth actions");
        const auto m = chunk_relative_motion(c.hidden_motion, clip.action_chunk);
        a.zero_();
        a.slice(1, data::slots::kLatent.begin, data::slots::kLatent.begin + m.size(1)).copy_(m);
        break;
      }
    }
    actions.push_back(a);
    pending_video.push_back(c.video);
    if (pending_video.size() == 8) flush();
    progress.advance();
  }
  flush();
  progress.finish();
  LatentClips clips{torch::cat(latents, 0).contiguous(), torch::stack(actions).contiguous(), spec_json};
  if (spec.mode == ActionMode::kGroundTruth) {
    // Motion deltas come in metres and radians; scale each dimension to a peak of 1 like the
    // min-max normalised robot actions.
    auto peak = clips.actions.abs().amax({0, 1}).clamp_min(1e-6);  // [384]
    clips.actions.div_(peak);
  }
  fs::create_directories(cache_file.parent_path().empty() ? fs::path(".") : cache_file.parent_path());
  save_safetensors(cache_file, {{"latents", clips.latents}, {"actions", clips.actions}},
                   {{"spec", spec_json.dump()}});
  LOG_INFO("latent cache: encoded ", clips.size(), " clips into ", cache_file.string());
  return clips;
}

LatentClips concat_latent_clips(const std::vector<LatentClips>& sets) {
  DOJO_CHECK(!sets.empty(), "no training data");
  std::vector<torch::Tensor> l, a;
  nlohmann::json meta = nlohmann::json::array();
  for (const auto& s : sets) {
    DOJO_CHECK(s.latents.sizes().slice(1) == sets[0].latents.sizes().slice(1),
               "latent caches disagree in shape: " + s.meta.value("dataset", std::string("?")) + " vs " +
                   sets[0].meta.value("dataset", std::string("?")) +
                   " (same frame size and tokenizer needed)");
    l.push_back(s.latents);
    a.push_back(s.actions);
    meta.push_back(s.meta);
  }
  return {torch::cat(l, 0), torch::cat(a, 0), meta};
}

}  // namespace dojo::train
