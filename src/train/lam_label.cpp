#include "train/lam_label.h"

#include <chrono>

#include "core/progress.h"
#include "core/safetensors.h"
#include "data/episode_store.h"

namespace dojo::train {

LamLabelSummary label_lam_dataset(models::LatentActionModel& model, const std::filesystem::path& dataset,
                                  std::filesystem::path out_dir, int64_t batch_pairs) {
  const auto t0 = std::chrono::steady_clock::now();
  auto store = data::EpisodeStore::open(dataset);
  if (out_dir.empty()) out_dir = dataset / "lam_latents";
  std::filesystem::create_directories(out_dir);
  LamLabelSummary s;
  Progress progress("lam label", static_cast<int64_t>(store.size()), "episode");
  for (size_t i = 0; i < store.size(); ++i) {
    const auto path = out_dir / (store.info().episodes[i].id + ".safetensors");
    if (!std::filesystem::exists(path)) {
      const auto mu =
          models::lam_encode_episode(model, store.load(i).frames, batch_pairs);  // [T - 1, latent]
      Metadata meta;
      meta["config"] = model->config.to_json().dump();
      save_safetensors(path, {{"z_mu", mu}}, meta);
      s.pairs += mu.size(0);
    }
    ++s.episodes;
    progress.advance();
  }
  progress.finish();
  s.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return s;
}

}  // namespace dojo::train
