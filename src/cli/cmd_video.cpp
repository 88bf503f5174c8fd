// `dojo video`: inspect videos and dump frames as PNG.
#include <torch/torch.h>
#include <CLI/CLI.hpp>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/error.h"
#include "core/log.h"
#include "core/progress.h"
#include "io/video.h"

namespace dojo::cli {
namespace {

void register_info(CLI::App& video) {
  auto* cmd =
      video.add_subcommand("info", "Print frame count, size, fps, codec and duration of a video file");
  auto file = std::make_shared<std::string>();
  auto json = std::make_shared<bool>(false);
  cmd->add_option("FILE", *file, "Video file (mp4, mkv, webm, avi, mov, ...)")->required();
  add_json_option(cmd, *json);
  cmd->callback([file, json] {
    set_action([file, json] {
      const io::VideoInfo info = io::probe_video(*file);
      if (*json) {
        std::printf("%s\n", info.to_json().dump(2).c_str());
      } else {
        std::printf("%-13s %s\n", "path", info.path.c_str());
        std::printf("%-13s %lld\n", "frames", static_cast<long long>(info.frames));
        std::printf("%-13s %d\n", "width", info.width);
        std::printf("%-13s %d\n", "height", info.height);
        std::printf("%-13s %.6g\n", "fps", info.fps);
        std::printf("%-13s %.3f s\n", "duration", info.duration_s);
        std::printf("%-13s %s\n", "codec", info.codec.c_str());
        std::printf("%-13s %s\n", "container", info.container.c_str());
        std::printf("%-13s %s\n", "pixel_format", info.pixel_format.c_str());
        std::printf("%-13s %lld\n", "keyframes", static_cast<long long>(info.keyframes));
      }
      return 0;
    });
  });
}

void register_frames(CLI::App& video) {
  auto* cmd = video.add_subcommand(
      "frames",
      "Decode frames and write them as PNG files OUT/frame_<index>.png (index = source frame number)");
  struct Options {
    std::string file, out, size;
    int64_t start = 0, count = -1, stride = 1;
    bool json = false;
  };
  auto o = std::make_shared<Options>();
  cmd->add_option("FILE", o->file, "Video file")->required();
  add_out_option(cmd, o->out, "directory for the frames (created when missing)")->required();
  cmd->add_option("--start", o->start, "First frame index")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cmd->add_option("--count", o->count, "Number of frames (-1 = through the end)")->capture_default_str();
  cmd->add_option("--stride", o->stride, "Take every S-th frame")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--size", o->size, "Center-crop to the HxW aspect, then resize to HxW (e.g. 256x256)");
  add_json_option(cmd, o->json);
  cmd->callback([o] {
    set_action([o] {
      int64_t out_h = 0, out_w = 0;
      if (!o->size.empty()) std::tie(out_h, out_w) = parse_size(o->size);
      if (o->count < -1) throw UsageError("--count must be >= 0, or -1 for all frames");
      io::VideoReader reader(o->file);
      const int64_t total = reader.num_frames();
      if (o->start >= total)
        throw UsageError("--start " + std::to_string(o->start) + " is past the last frame of '" + o->file +
                         "' (" + std::to_string(total) + " frames)");
      const int64_t available = (total - o->start + o->stride - 1) / o->stride;
      const int64_t count = o->count < 0 ? available : std::min(o->count, available);
      if (o->count > available)
        LOG_WARN("'", o->file, "' has ", available, " frames from --start with this --stride; writing those");
      std::filesystem::create_directories(o->out);
      Progress progress("frames", count, "frame");
      nlohmann::json written = nlohmann::json::array();
      reader.for_each_frame(o->start, count, o->stride, [&](int64_t index, const at::Tensor& frame) {
        const auto image = out_h > 0 ? io::resize_center_crop(frame, out_h, out_w) : frame;
        const auto paths = io::write_png_frames(o->out, image.unsqueeze(0), "frame_", index);
        written.push_back(paths.front());
        progress.advance();
      });
      progress.finish();
      if (o->json) {
        std::printf("%s\n", nlohmann::json{{"source", o->file}, {"files", written}}.dump(2).c_str());
      } else {
        std::printf("wrote %lld PNG frames to %s\n", static_cast<long long>(written.size()), o->out.c_str());
      }
      return 0;
    });
  });
}

}  // namespace

void register_video(CLI::App& app) {
  auto* video = app.add_subcommand("video", "Video files: inspect, dump frames");
  video->require_subcommand(1);
  register_info(*video);
  register_frames(*video);
}

}  // namespace dojo::cli
