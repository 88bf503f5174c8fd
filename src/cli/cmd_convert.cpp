// `dojo convert SRC DST`: a released checkpoint (DCP folder, .pt / .pth / .ckpt) -> a checkpoint
// directory of this engine, with nothing in the file executed (models/released_import.h).
#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdio>
#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/error.h"
#include "core/json_file.h"
#include "models/released_import.h"

namespace dojo::cli {

void register_convert(CLI::App& app) {
  auto* cmd = app.add_subcommand(
      "convert",
      "Convert a released DreamDojo DiT, LAM or Wan2.1 VAE checkpoint (DCP folder, .pt, .pth, .ckpt) "
      "into a checkpoint directory, without running code from the file");
  struct Args {
    std::string src, dst, model = "auto", lora = "merge", dtype = "keep", entry, config;
    bool trained = false, json = false;
    double lora_alpha = 32.0;
    std::vector<std::string> allow_globals;
  };
  auto args = std::make_shared<Args>();
  cmd->add_option("SRC", args->src,
                  "A DCP folder (checkpoints/, iter_NNNNNNNNN/ or its model/), or a torch.save file")
      ->required();
  cmd->add_option("DST", args->dst, "Output checkpoint directory")->required();
  cmd->add_option("--model", args->model, "auto | dit | lam | wan21_vae")->capture_default_str();
  cmd->add_flag("--trained", args->trained,
                "DiT: take the trained weights (net.*) instead of the EMA (net_ema.*)");
  cmd->add_option("--lora", args->lora,
                  "PEFT LoRA tensors: merge (W + alpha/r B A) | keep (adapter_model.safetensors)")
      ->check(CLI::IsMember({"merge", "keep"}))
      ->capture_default_str();
  cmd->add_option("--lora-alpha", args->lora_alpha, "LoRA alpha (the scale is alpha / rank)")
      ->capture_default_str();
  cmd->add_option("--dtype", args->dtype, "keep | bf16 | fp16 | fp32: the learned weights' dtype")
      ->check(CLI::IsMember({"keep", "bf16", "fp16", "fp32"}))
      ->capture_default_str();
  cmd->add_option(
      "--entry", args->entry,
      "The dict entry holding the weights (default: state_dict when present, else the whole file)");
  cmd->add_option("--config", args->config,
                  "A JSON file of config fields that override those read from the shapes");
  cmd->add_option(
      "--allow-global", args->allow_globals,
      "Accept this pickled global (module.Name) as an inert record; repeatable. Nothing is ever run");
  add_json_option(cmd, args->json);
  cmd->callback([args] {
    set_action([args] {
      models::ImportOptions options;
      options.model = models::parse_released_model(args->model);
      options.trained = args->trained;
      options.merge_lora = args->lora == "merge";
      options.lora_alpha = args->lora_alpha;
      if (args->dtype != "keep")
        options.dtype = args->dtype == "bf16"   ? torch::kBFloat16
                        : args->dtype == "fp16" ? torch::kHalf
                                                : torch::kFloat;
      options.entry = args->entry;
      if (!args->config.empty()) options.config_overrides = read_json_file(args->config);
      options.file.extra_globals = args->allow_globals;
      const auto start = std::chrono::steady_clock::now();
      const auto report = models::import_released(args->src, args->dst, options);
      const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      if (args->json) {
        nlohmann::ordered_json out = {{"source", args->src},
                                      {"destination", args->dst},
                                      {"model", report.model},
                                      {"format", report.source_format},
                                      {"weights", report.selection},
                                      {"tensors", report.tensors},
                                      {"parameters", report.parameters},
                                      {"lora_layers", report.lora_adapters},
                                      {"skipped", report.skipped.size()},
                                      {"seconds", seconds},
                                      {"config", report.config}};
        std::printf("%s\n", out.dump(2).c_str());
      } else {
        std::printf("%s (%s%s) -> %s: %s, %lld tensors, %lld parameters", args->src.c_str(),
                    report.source_format.c_str(),
                    report.selection.empty() ? "" : (", " + report.selection).c_str(), args->dst.c_str(),
                    report.model.c_str(), static_cast<long long>(report.tensors),
                    static_cast<long long>(report.parameters));
        if (report.lora_adapters)
          std::printf(", %lld LoRA layers %s", static_cast<long long>(report.lora_adapters),
                      options.merge_lora ? "merged" : "kept");
        if (!report.skipped.empty()) std::printf(", %zu entries skipped", report.skipped.size());
        std::printf(" (%.1f s)\n", seconds);
      }
      return 0;
    });
  });
}

}  // namespace dojo::cli
