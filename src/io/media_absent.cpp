// The video and JPEG entry points of a build without FFmpeg and libjpeg-turbo (CMake
// DOJO_WITH_MEDIA=OFF): the trainers on a machine that has only a C++ toolchain and PyTorch's
// libtorch, such as a rented GPU. Each throws one line naming the file it was asked for; datasets
// of raw frames (data::VideoFormat::kRaw, `--video-format raw`) need none of them. The normal
// build compiles video_reader.cpp, video_writer.cpp and jpeg.cpp instead of this file.
#include <string>

#include "core/error.h"
#include "io/jpeg.h"
#include "io/video.h"

namespace dojo::io {

namespace {

[[noreturn]] void absent(const std::string& what) {
  throw Error(what +
              ": this dojo was built without video support (DOJO_WITH_MEDIA=OFF): give datasets of raw "
              "frames (dojo data convert SRC DST --video-format raw) or use a full build");
}

}  // namespace

struct VideoReader::Impl {};

VideoReader::VideoReader(const std::string& path, VideoReaderOptions) { absent(path); }
VideoReader::~VideoReader() = default;
VideoReader::VideoReader(VideoReader&&) noexcept = default;
VideoReader& VideoReader::operator=(VideoReader&&) noexcept = default;
const VideoInfo& VideoReader::info() const { absent("a video"); }
int64_t VideoReader::num_frames() const { absent("a video"); }
const std::string& VideoReader::path() const { absent("a video"); }
at::Tensor VideoReader::read_frame(int64_t) { absent("a video"); }
at::Tensor VideoReader::read_frames(const std::vector<int64_t>&) { absent("a video"); }
at::Tensor VideoReader::read_range(int64_t, int64_t, int64_t) { absent("a video"); }
at::Tensor VideoReader::read_all() { absent("a video"); }
void VideoReader::for_each_frame(int64_t, int64_t, int64_t,
                                 const std::function<void(int64_t, const at::Tensor&)>&) {
  absent("a video");
}

VideoInfo probe_video(const std::string& path) { absent(path); }
double measure_decode_fps(const std::string& path, int, VideoReaderOptions, int64_t) { absent(path); }

struct VideoWriter::Impl {};

VideoWriter::VideoWriter(const std::string& path, VideoWriterOptions) { absent(path); }
VideoWriter::~VideoWriter() = default;
void VideoWriter::write(const at::Tensor&) { absent("a video"); }
void VideoWriter::write_many(const at::Tensor&) { absent("a video"); }
void VideoWriter::close() { absent("a video"); }
int64_t VideoWriter::frames_written() const { absent("a video"); }
const std::string& VideoWriter::path() const { absent("a video"); }

void write_video(const std::string& path, const at::Tensor&, const VideoWriterOptions&) { absent(path); }
void write_png(const std::string& path, const at::Tensor&) { absent(path); }
std::vector<std::string> write_png_frames(const std::string& dir, const at::Tensor&, const std::string&,
                                          int64_t) {
  absent(dir);
}

std::string encode_jpeg(const at::Tensor&, int) { absent("a JPEG frame"); }
at::Tensor decode_jpeg(std::string_view, const std::string& what) { absent(what); }

}  // namespace dojo::io
