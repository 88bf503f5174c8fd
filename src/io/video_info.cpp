// VideoInfo::to_json, apart from the FFmpeg reader so a build without FFmpeg
// (io/media_absent.cpp) has it too.
#include <nlohmann/json.hpp>

#include "io/video.h"

namespace dojo::io {

nlohmann::json VideoInfo::to_json() const {
  return {{"path", path},
          {"frames", frames},
          {"width", width},
          {"height", height},
          {"fps", fps},
          {"codec", codec},
          {"container", container},
          {"duration_s", duration_s},
          {"pixel_format", pixel_format},
          {"keyframes", keyframes}};
}

}  // namespace dojo::io
