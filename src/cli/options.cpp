#include "cli/options.h"

#include <CLI/CLI.hpp>

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "core/error.h"
#include "core/runtime.h"

namespace dojo::cli {

const std::vector<SharedOption>& shared_options() {
  static const std::vector<SharedOption> table = {
      {"--device", "Where the networks run: cpu | cuda | cuda:N | auto"},
      {"--precision", "fp32 | bf16 | fp16 (CUDA only): matmuls under autocast, weights stay fp32"},
      {"--data,-d", "Dataset directory (episode store, LeRobot, EgoDex or video folder)"},
      {"--split,-s", "Dataset split (train, val, ..., or all)"},
      {"--seed", "Random seed: the same seed gives the same result"},
      {"--workers,-j", "Worker threads for data generation and loading (0 = all cores)"},
      {"--json", "Print the result as JSON"},
      {"--out,-o", "Output"},
      {"--checkpoint,--ckpt,-c", "Checkpoint directory"},
      {"--video-format",
       "How the episodes store their frames: mp4 (H.264) or raw (the uint8 frames in safetensors, ~10x "
       "larger, read and written with no video library)"},
      {"--accumulate",
       "Micro-batches per step and process: the batch splits over processes x accumulate "
       "(dojo launch); gradients add up before one optimiser step"},
  };
  return table;
}

namespace {

const SharedOption& shared(const std::string& names) {
  for (const auto& o : shared_options())
    if (o.names == names) return o;
  throw std::logic_error("no shared option " + names);
}

}  // namespace

CLI::Option* add_device_option(CLI::App* cmd, std::string& device) {
  const auto& o = shared("--device");
  return cmd->add_option(o.names, device, o.help)->capture_default_str();
}

CLI::Option* add_precision_option(CLI::App* cmd, std::string& precision) {
  const auto& o = shared("--precision");
  return cmd->add_option(o.names, precision, o.help)->capture_default_str();
}

CLI::Option* add_video_format_option(CLI::App* cmd, std::string& format) {
  const auto& o = shared("--video-format");
  return cmd->add_option(o.names, format, o.help)
      ->check(CLI::IsMember({"mp4", "raw"}))
      ->capture_default_str();
}

void TrainingDeviceArgs::add_to(CLI::App* cmd) {
  add_device_option(cmd, device);
  add_precision_option(cmd, precision);
}

TrainingDeviceArgs::Parsed TrainingDeviceArgs::parse(const std::string& trainer) const {
  Parsed p{parse_device(device), parse_precision(precision)};
  check_training_precision(trainer, p.precision);
  check_precision_supported(p.precision, p.device.type());
  return p;
}

CLI::Option* add_data_option(CLI::App* cmd, std::string& dir) {
  const auto& o = shared("--data,-d");
  return cmd->add_option(o.names, dir, o.help);
}

CLI::Option* add_data_option(CLI::App* cmd, std::vector<std::string>& dirs, const std::string& extra) {
  const auto& o = shared("--data,-d");
  return cmd->add_option(o.names, dirs,
                         o.help + "; repeat for several" + (extra.empty() ? "" : "; " + extra));
}

CLI::Option* add_split_option(CLI::App* cmd, std::string& split) {
  const auto& o = shared("--split,-s");
  return cmd->add_option(o.names, split, o.help)->capture_default_str();
}

CLI::Option* add_split_option(CLI::App* cmd, std::vector<std::string>& splits) {
  const auto& o = shared("--split,-s");
  return cmd->add_option(o.names, splits, o.help + "; repeat for several")->capture_default_str();
}

CLI::Option* add_seed_option(CLI::App* cmd, uint64_t& seed) {
  const auto& o = shared("--seed");
  return cmd->add_option(o.names, seed, o.help)->capture_default_str();
}

CLI::Option* add_accumulate_option(CLI::App* cmd, int64_t& accumulate) {
  const auto& o = shared("--accumulate");
  return cmd->add_option(o.names, accumulate, o.help)
      ->check(CLI::Range(int64_t{1}, int64_t{4096}))
      ->capture_default_str();
}

CLI::Option* add_workers_option(CLI::App* cmd, int& workers) {
  const auto& o = shared("--workers,-j");
  return cmd->add_option(o.names, workers, o.help)->check(CLI::NonNegativeNumber)->capture_default_str();
}

CLI::Option* add_json_option(CLI::App* cmd, bool& json) {
  const auto& o = shared("--json");
  return cmd->add_flag(o.names, json, o.help);
}

CLI::Option* add_out_option(CLI::App* cmd, std::string& out, const std::string& what) {
  const auto& o = shared("--out,-o");
  return cmd->add_option(o.names, out, o.help + ": " + what);
}

CLI::Option* add_checkpoint_option(CLI::App* cmd, std::string& dir, const std::string& what) {
  const auto& o = shared("--checkpoint,--ckpt,-c");
  return cmd->add_option(o.names, dir, o.help + ": " + what);
}

WeightedData parse_weighted_data(const std::string& text) {
  const auto colon = text.rfind(':');
  if (colon == std::string::npos || colon == 0) return {text};
  const auto tail = text.substr(colon + 1);
  // A path may hold colons of its own: only a numeric tail is a weight.
  if (tail.empty() || tail.find_first_not_of("0123456789.eE+-") != std::string::npos) return {text};
  try {
    size_t used = 0;
    const double weight = std::stod(tail, &used);
    if (used != tail.size() || !(weight > 0) || !std::isfinite(weight)) throw std::invalid_argument("weight");
    return {text.substr(0, colon), weight, true};
  } catch (const std::exception&) {
    throw UsageError("--data must look like DIR or DIR:WEIGHT with WEIGHT > 0, got '" + text + "'");
  }
}

void add_views_options(CLI::App* cmd, std::vector<std::string>& views, std::string& layout,
                       const std::string& what) {
  cmd->add_option("--views", views,
                  "Cameras tiled into one canvas, the main one first (e.g. ego,side; LeRobot: video keys or "
                  "modality names); " +
                      what)
      ->delimiter(',');
  cmd->add_option("--view-layout", layout, "How --views are tiled: side_by_side, stack or grid")
      ->check(CLI::IsMember({"side_by_side", "stack", "grid"}))
      ->capture_default_str();
}

std::vector<double> mixture_weights(const std::vector<WeightedData>& data) {
  std::vector<double> weights;
  if (std::any_of(data.begin(), data.end(), [](const WeightedData& d) { return d.weighted; }))
    for (const auto& d : data) weights.push_back(d.weight);
  return weights;
}

}  // namespace dojo::cli
