#include "eval/tokenizer_eval.h"

#include "core/error.h"
#include "core/progress.h"
#include "data/clip_loader.h"
#include "data/episode_source.h"
#include "eval/metrics.h"

namespace dojo::eval {

nlohmann::json TokenizerEvalResult::to_json() const {
  return {{"psnr", psnr}, {"ssim", ssim}, {"clips", clips}, {"frames", frames}};
}

TokenizerEvalResult evaluate_tokenizer(models::WanVae& vae, const std::filesystem::path& dataset,
                                       const TokenizerEvalOptions& o) {
  DOJO_CHECK(o.frames > 0 && (o.frames - 1) % 4 == 0,
             "tokenizer eval: --frames must be 1 + 4k (got " + std::to_string(o.frames) + ")");
  DOJO_CHECK(o.clips > 0, "tokenizer eval: --clips must be positive");
  const auto source = data::open_dataset(dataset);
  data::ClipConfig clip;
  clip.num_frames = o.frames;
  clip.strides = {1};
  clip.height = o.size > 0 ? o.size : source->info().height;
  clip.width = o.size > 0 ? o.size : source->info().width;
  data::ClipDataset clips(source, clip, o.split);
  DOJO_CHECK(!clips.episodes().empty(), dataset.string() + ": no episodes in split '" + o.split + "'");
  TokenizerEvalResult r;
  r.clips = o.clips;
  r.frames = o.frames;
  std::vector<VideoMetrics> per_clip;
  Progress progress("tokenizer eval", o.clips, "clip");
  for (int i = 0; i < o.clips; ++i) {
    auto rng = data::stream_rng(o.seed, static_cast<uint64_t>(i));
    const auto original = clips.sample(rng).video;                                 // [T, H, W, 3]
    const auto recon = models::reconstruct_frames(vae, original.unsqueeze(0))[0];  // [T, H, W, 3]
    per_clip.push_back(video_metrics(recon, original));
    if (static_cast<int>(r.originals.size()) < o.keep_examples) {
      r.originals.push_back(original);
      r.reconstructions.push_back(recon);
    }
    progress.advance();
  }
  progress.finish();
  const auto mean = dataset_mean(per_clip);
  r.psnr = mean.psnr;
  r.ssim = mean.ssim;
  return r;
}

}  // namespace dojo::eval
