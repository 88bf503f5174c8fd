// `dojo metrics video`: PSNR / SSIM (piq conventions) and optionally LPIPS-VGG between a predicted
// and a ground-truth video, per frame then averaged; `dojo metrics policies`: how well world-model
// success rates rank policies against real ones (Pearson r, MMRV, Spearman; docs/evaluation.md).
#include <torch/torch.h>
#include <CLI/CLI.hpp>
#include <cmath>
#include <cstdio>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/error.h"
#include "core/log.h"
#include "eval/lpips.h"
#include "eval/metrics.h"
#include "io/video.h"

namespace dojo::cli {

namespace {

void add_video(CLI::App& metrics) {
  auto* cmd = metrics.add_subcommand(
      "video", "PSNR, SSIM (and LPIPS with --lpips-weights) of a predicted video against ground truth");
  struct Options {
    std::string pred, gt;
    std::vector<std::string> lpips_weights;
    int64_t frames = -1;
    bool json = false;
  };
  auto o = std::make_shared<Options>();
  cmd->add_option("PRED", o->pred, "Predicted video")->required();
  cmd->add_option("GT", o->gt, "Ground-truth video (same size)")->required();
  cmd->add_option("--lpips-weights", o->lpips_weights,
                  "LPIPS-VGG weights as safetensors (one file or trunk + heads; see docs/evaluation.md)");
  cmd->add_option("--frames", o->frames, "Compare the first N frames (-1 = as many as both have)")
      ->capture_default_str();
  add_json_option(cmd, o->json);
  cmd->callback([o] {
    set_action([o] {
      std::optional<eval::Lpips> lpips;
      if (!o->lpips_weights.empty()) {
        std::vector<std::filesystem::path> files(o->lpips_weights.begin(), o->lpips_weights.end());
        lpips = eval::Lpips::load(files);
      }
      auto pred = io::VideoReader(o->pred).read_all();  // [N, H, W, 3] uint8
      auto gt = io::VideoReader(o->gt).read_all();
      DOJO_CHECK(pred.sizes().slice(1) == gt.sizes().slice(1),
                 "metrics: '" + o->pred + "' and '" + o->gt + "' differ in frame size");
      int64_t n = std::min(pred.size(0), gt.size(0));
      if (o->frames >= 0) n = std::min(n, o->frames);
      DOJO_CHECK(n > 0, "metrics: no frames to compare");
      if (pred.size(0) != gt.size(0))
        LOG_WARN("frame counts differ (", pred.size(0), " vs ", gt.size(0), "); comparing the first ", n);
      const auto m = eval::video_metrics(pred.narrow(0, 0, n), gt.narrow(0, 0, n), lpips ? &*lpips : nullptr);
      if (o->json) {
        nlohmann::json j;
        j["pred"] = o->pred;
        j["gt"] = o->gt;
        j["frames"] = m.num_frames;
        j["psnr"] = m.psnr;
        j["ssim"] = m.ssim;
        j["lpips"] = std::isnan(m.lpips) ? nlohmann::json(nullptr) : nlohmann::json(m.lpips);
        std::printf("%s\n", j.dump(2).c_str());
      } else {
        std::printf("%-7s %lld\n", "frames", static_cast<long long>(m.num_frames));
        std::printf("%-7s %.4f dB\n", "psnr", m.psnr);
        std::printf("%-7s %.5f\n", "ssim", m.ssim);
        if (!std::isnan(m.lpips)) std::printf("%-7s %.5f\n", "lpips", m.lpips);
      }
      return 0;
    });
  });
}

void add_policies(CLI::App& metrics) {
  auto* cmd = metrics.add_subcommand(
      "policies",
      "Pearson r, MMRV, Spearman rho and the mean absolute gap between per-policy success rates in the "
      "world model and in the real world, from FILE.json: {\"policies\": [{\"name\": ..., \"world_model\": "
      "0.8, \"real\": 0.7}, ...]}");
  auto file = std::make_shared<std::string>();
  auto json = std::make_shared<bool>(false);
  cmd->add_option("FILE", *file, "JSON file of per-policy success rates")->required();
  add_json_option(cmd, *json);
  cmd->callback([file, json] {
    set_action([file, json] {
      const auto rates = eval::read_policy_rates(*file);
      const auto a = eval::policy_agreement(rates);
      if (*json) {
        auto j = a.to_json();
        j["policies"] = static_cast<int64_t>(rates.names.size());
        std::printf("%s\n", j.dump(2).c_str());
      } else {
        std::printf("%-13s %zu\n", "policies", rates.names.size());
        std::printf("%-13s %.4f\n", "pearson r", a.pearson);
        std::printf("%-13s %.4f\n", "mmrv", a.mmrv);
        std::printf("%-13s %.4f\n", "spearman rho", a.spearman);
        std::printf("%-13s %.4f\n", "mean |gap|", a.mean_abs_gap);
      }
      return 0;
    });
  });
}

}  // namespace

void register_metrics(CLI::App& app) {
  auto* metrics = app.add_subcommand("metrics", "Metrics of videos and of policy rankings");
  metrics->require_subcommand(1);
  add_video(*metrics);
  add_policies(*metrics);
}

}  // namespace dojo::cli
