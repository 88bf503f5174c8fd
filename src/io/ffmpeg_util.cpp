// FFmpeg plumbing shared by the video reader and writer (see ffmpeg_util.h).
#include "io/ffmpeg_util.h"

#include <torch/torch.h>

#include <cstdarg>
#include <mutex>
#include <string>

#include "core/error.h"
#include "core/log.h"

extern "C" {
#include <libavutil/pixdesc.h>
}

namespace dojo::io::video_detail {

std::string av_error(int code) {
  char buffer[AV_ERROR_MAX_STRING_SIZE] = {0};
  av_strerror(code, buffer, sizeof(buffer));
  return buffer;
}

namespace {

// FFmpeg logs per call fragments of lines; join them and hand whole lines to LOG_DEBUG so a
// corrupt file does not spray warnings over the user's terminal (our errors say what failed).
void ffmpeg_log_callback(void* avcl, int level, const char* fmt, va_list vl) {
  if (level > AV_LOG_WARNING || log_level() > LogLevel::kDebug) return;
  thread_local int print_prefix = 1;
  thread_local std::string pending;
  char line[1024];
  av_log_format_line2(avcl, level, fmt, vl, line, sizeof(line), &print_prefix);
  pending += line;
  if (!pending.empty() && pending.back() == '\n') {
    pending.pop_back();
    LOG_DEBUG("ffmpeg: ", pending);
    pending.clear();
  }
}

}  // namespace

void init_ffmpeg() {
  static std::once_flag once;
  std::call_once(once, [] {
    av_log_set_level(AV_LOG_WARNING);
    av_log_set_callback(ffmpeg_log_callback);
  });
}

FramePtr make_frame() {
  FramePtr frame(av_frame_alloc());
  if (!frame) throw Error("out of memory allocating a video frame");
  return frame;
}
PacketPtr make_packet() {
  PacketPtr packet(av_packet_alloc());
  if (!packet) throw Error("out of memory allocating a video packet");
  return packet;
}

namespace {

bool is_full_range(const AVFrame* frame) {
  switch (frame->format) {
    case AV_PIX_FMT_YUVJ420P:
    case AV_PIX_FMT_YUVJ422P:
    case AV_PIX_FMT_YUVJ444P:
    case AV_PIX_FMT_YUVJ440P:
      return true;
    default:
      return frame->color_range == AVCOL_RANGE_JPEG;
  }
}

// The YUV matrix of a frame; untagged streams follow the usual player convention (BT.709 for
// HD sizes, BT.601 for SD).
int sws_colorspace(const AVFrame* frame) {
  switch (frame->colorspace) {
    case AVCOL_SPC_BT709:
      return SWS_CS_ITU709;
    case AVCOL_SPC_BT470BG:
    case AVCOL_SPC_SMPTE170M:
      return SWS_CS_ITU601;
    case AVCOL_SPC_SMPTE240M:
      return SWS_CS_SMPTE240M;
    case AVCOL_SPC_FCC:
      return SWS_CS_FCC;
    case AVCOL_SPC_BT2020_NCL:
    case AVCOL_SPC_BT2020_CL:
      return SWS_CS_BT2020;
    default:
      return (frame->width >= 1280 || frame->height > 576) ? SWS_CS_ITU709 : SWS_CS_ITU601;
  }
}

}  // namespace

void RgbConverter::convert(const AVFrame* frame, int out_w, int out_h, uint8_t* dst) {
  const int colorspace = sws_colorspace(frame);
  const int full_range = is_full_range(frame) ? 1 : 0;
  if (!sws_ || frame->format != src_format_ || frame->width != src_w_ || frame->height != src_h_ ||
      out_w != dst_w_ || out_h != dst_h_ || colorspace != colorspace_ || full_range != full_range_) {
    // yuvj* formats are deprecated aliases; sws wants the plain format plus the range flag.
    AVPixelFormat format = static_cast<AVPixelFormat>(frame->format);
    if (format == AV_PIX_FMT_YUVJ420P) format = AV_PIX_FMT_YUV420P;
    if (format == AV_PIX_FMT_YUVJ422P) format = AV_PIX_FMT_YUV422P;
    if (format == AV_PIX_FMT_YUVJ444P) format = AV_PIX_FMT_YUV444P;
    if (format == AV_PIX_FMT_YUVJ440P) format = AV_PIX_FMT_YUV440P;
    sws_.reset(sws_getContext(frame->width, frame->height, format, out_w, out_h, AV_PIX_FMT_RGB24, flags_,
                              nullptr, nullptr, nullptr));
    if (!sws_) throw Error("cannot convert pixel format " + pixel_format_name(frame->format) + " to RGB");
    sws_setColorspaceDetails(sws_.get(), sws_getCoefficients(colorspace), full_range,
                             sws_getCoefficients(SWS_CS_DEFAULT), 1, 0, 1 << 16, 1 << 16);
    src_format_ = frame->format;
    src_w_ = frame->width;
    src_h_ = frame->height;
    dst_w_ = out_w;
    dst_h_ = out_h;
    colorspace_ = colorspace;
    full_range_ = full_range;
  }
  uint8_t* dst_planes[4] = {dst, nullptr, nullptr, nullptr};
  int dst_strides[4] = {out_w * 3, 0, 0, 0};
  sws_scale(sws_.get(), frame->data, frame->linesize, 0, frame->height, dst_planes, dst_strides);
}

std::string RgbConverter::pixel_format_name(int format) {
  const char* name = av_get_pix_fmt_name(static_cast<AVPixelFormat>(format));
  return name ? name : "unknown";
}

}  // namespace dojo::io::video_detail
