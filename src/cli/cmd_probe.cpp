// `dojo probe train|eval`: the keypoint probe that finds the embodiment in a frame.
#include <CLI/CLI.hpp>

#include <cstdio>
#include <filesystem>
#include <memory>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/runtime.h"
#include "eval/keypoint_metrics.h"
#include "models/keypoint_probe.h"
#include "train/probe_train.h"

namespace dojo::cli {
namespace {

void add_probe_train(CLI::App& probe) {
  auto* cmd = probe.add_subcommand(
      "train",
      "Train the keypoint probe on DojoSim episodes (robot and human) labelled by the simulator; "
      "resumes from OUT/checkpoint");
  auto job = std::make_shared<train::ProbeTrainJob>();
  auto data = std::make_shared<std::vector<std::string>>();
  auto out = std::make_shared<std::string>();
  auto minutes = std::make_shared<double>(0);
  auto device = std::make_shared<TrainingDeviceArgs>();
  add_data_option(cmd, *data)->required();
  add_split_option(cmd, job->split);
  add_out_option(cmd, *out, "directory for checkpoint/ and loss.csv")->required();
  cmd->add_option("--steps", job->steps, "Total optimisation steps")->capture_default_str();
  cmd->add_option("--minutes", *minutes, "Stop (and checkpoint) after this many minutes; 0 = no limit")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--batch,-b", job->batch_size, "Frames per step")->capture_default_str();
  add_accumulate_option(cmd, job->accumulate);
  cmd->add_option("--lr", job->lr, "AdamW learning rate")->capture_default_str();
  cmd->add_option("--size", job->model.size, "Probe input size (frames are resized to SIZE x SIZE)")
      ->capture_default_str();
  cmd->add_option("--width", job->model.width, "Channels of the first stage")->capture_default_str();
  cmd->add_option("--save-every", job->save_every, "Checkpoint interval in steps")->capture_default_str();
  add_seed_option(cmd, job->seed);
  device->add_to(cmd);
  cmd->callback([=] {
    set_action([=] {
      device->set_in(*job, "probe train");
      job->datasets.assign(data->begin(), data->end());
      job->out = *out;
      job->time_budget_s = *minutes * 60.0;
      const auto r = train::run_probe_training(*job);
      std::printf("probe train: %lld steps, loss %.4f, %.0f frames/s; checkpoint %s\n",
                  static_cast<long long>(r.steps), r.loss, r.frames_per_second,
                  (job->out / "checkpoint").string().c_str());
      return 0;
    });
  });
}

void add_eval(CLI::App& probe) {
  auto* cmd = probe.add_subcommand(
      "eval", "Keypoint error, recall and false positives of the probe on real frames of a split");
  auto ckpt = std::make_shared<std::string>();
  auto data = std::make_shared<std::vector<std::string>>();
  auto split = std::make_shared<std::string>("val");
  auto json = std::make_shared<bool>(false);
  add_checkpoint_option(cmd, *ckpt, "the keypoint probe")->required();
  add_data_option(cmd, *data)->required();
  add_split_option(cmd, *split);
  add_json_option(cmd, *json);
  cmd->callback([=] {
    set_action([=] {
      auto probe = models::load_keypoint_probe(*ckpt);
      const std::vector<std::filesystem::path> dirs(data->begin(), data->end());
      const auto a = eval::probe_accuracy(probe, dirs, *split);
      if (*json) {
        std::printf("%s\n", a.to_json().dump(2).c_str());
      } else {
        std::printf("%lld frames: keypoint error %.2f px, recall %.3f, false positives %.3f\n",
                    static_cast<long long>(a.frames), a.error_px, a.recall, a.false_positive);
      }
      return 0;
    });
  });
}

}  // namespace

void register_probe(CLI::App& app) {
  auto* probe = app.add_subcommand("probe", "Keypoint probe: where the embodiment is in a frame");
  probe->require_subcommand(1);
  add_probe_train(*probe);
  add_eval(*probe);
}

}  // namespace dojo::cli
