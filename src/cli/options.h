// The options many `dojo` commands share, defined once: every command that takes one of these
// gets the same name, the same alias and the same help text. Commands add the ones they use.
#pragma once

#include <c10/core/Device.h>

#include <cstdint>
#include <string>
#include <vector>

#include "core/autocast.h"

namespace CLI {
class App;
class Option;
}  // namespace CLI

namespace dojo::cli {

CLI::Option* add_device_option(CLI::App* cmd, std::string& device);        // --device
CLI::Option* add_precision_option(CLI::App* cmd, std::string& precision);  // --precision
// A trainer's --device and --precision. parse() checks them before any work, each failure one
// line: an unknown name, a CUDA request without CUDA, fp16 (no trainer scales its loss), or a
// precision the device cannot run.
struct TrainingDeviceArgs {
  std::string device = "cpu", precision = "fp32";
  void add_to(CLI::App* cmd);
  struct Parsed {
    c10::Device device;
    Precision precision;
  };
  Parsed parse(const std::string& trainer) const;
  // parse(trainer) into a job's (or run's) `device` and `precision`.
  template <class Job>
  void set_in(Job& job, const std::string& trainer) const {
    const auto p = parse(trainer);
    job.device = p.device;
    job.precision = p.precision;
  }
};
CLI::Option* add_data_option(CLI::App* cmd, std::string& dir);  // --data,-d
// --data,-d, repeatable; `extra` is appended to the help (what else the value may say).
CLI::Option* add_data_option(CLI::App* cmd, std::vector<std::string>& dirs, const std::string& extra = "");
CLI::Option* add_split_option(CLI::App* cmd, std::string& split);  // --split,-s
CLI::Option* add_split_option(CLI::App* cmd, std::vector<std::string>& splits);
CLI::Option* add_seed_option(CLI::App* cmd, uint64_t& seed);               // --seed
CLI::Option* add_workers_option(CLI::App* cmd, int& workers);              // --workers,-j
CLI::Option* add_accumulate_option(CLI::App* cmd, int64_t& accumulate);    // --accumulate (data parallelism)
CLI::Option* add_json_option(CLI::App* cmd, bool& json);                   // --json
CLI::Option* add_video_format_option(CLI::App* cmd, std::string& format);  // --video-format mp4|raw
// A --data value "DIR" or "DIR:WEIGHT" (a mixture weight > 0; a colon not followed by a number
// belongs to the path). Throws dojo::UsageError naming the value.
struct WeightedData {
  std::string dir;
  double weight = 1.0;
  bool weighted = false;  // the value gave a weight
};
WeightedData parse_weighted_data(const std::string& text);
// --views CAM,CAM[,...] and --view-layout: several cameras of each dataset tiled into one canvas
// (data/multi_view.h). `what` says where the default comes from.
void add_views_options(CLI::App* cmd, std::vector<std::string>& views, std::string& layout,
                       const std::string& what);
// The mixture weights of a trainer's --data values: one weight given anywhere weighs every dataset
// (1 where none is given); none at all gives {} (every clip alike).
std::vector<double> mixture_weights(const std::vector<WeightedData>& data);
// --out,-o: `what` says what the command writes there (a checkpoint directory, an mp4, ...).
CLI::Option* add_out_option(CLI::App* cmd, std::string& out, const std::string& what);
// --checkpoint,--ckpt,-c: `what` names the model the checkpoint holds.
CLI::Option* add_checkpoint_option(CLI::App* cmd, std::string& dir, const std::string& what);

// The names, aliases and help texts above, for `dojo --help` checks and the docs.
struct SharedOption {
  std::string names, help;
};
const std::vector<SharedOption>& shared_options();

}  // namespace dojo::cli
