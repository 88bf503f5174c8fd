// Internal to src/io (not a public header): what the video .cpp files share. FFmpeg plumbing
// for video_reader.cpp and video_writer.cpp (error strings, log routing, one-time init, owning
// pointers, RGB conversion).
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>
#include <memory>
#include <string>

extern "C" {
#include <libavcodec/avcodec.h>
#include <libavformat/avformat.h>
#include <libswscale/swscale.h>
}

namespace dojo::io::video_detail {

std::string av_error(int code);

// Sends FFmpeg's log output to LOG_DEBUG (once per process; cheap to call again).
void init_ffmpeg();

struct FormatInputDeleter {
  void operator()(AVFormatContext* p) const { avformat_close_input(&p); }
};
struct CodecDeleter {
  void operator()(AVCodecContext* p) const { avcodec_free_context(&p); }
};
struct FrameDeleter {
  void operator()(AVFrame* p) const { av_frame_free(&p); }
};
struct PacketDeleter {
  void operator()(AVPacket* p) const { av_packet_free(&p); }
};
struct SwsDeleter {
  void operator()(SwsContext* p) const { sws_freeContext(p); }
};
using FormatInputPtr = std::unique_ptr<AVFormatContext, FormatInputDeleter>;
using CodecPtr = std::unique_ptr<AVCodecContext, CodecDeleter>;
using FramePtr = std::unique_ptr<AVFrame, FrameDeleter>;
using PacketPtr = std::unique_ptr<AVPacket, PacketDeleter>;
using SwsPtr = std::unique_ptr<SwsContext, SwsDeleter>;

FramePtr make_frame();
PacketPtr make_packet();

// Converts decoded frames of any pixel format/size to packed RGB24 of a fixed output size.
class RgbConverter {
 public:
  // Accurate: chroma interpolated bilinearly and exact rounding (what `ffmpeg -sws_flags
  // bilinear+accurate_rnd+full_chroma_int` gives). Fast: swscale's SIMD path, nearest chroma and
  // colours 1-2 levels dark; about 3x faster, which matters only when conversion dominates.
  explicit RgbConverter(bool accurate)
      : flags_(accurate ? SWS_BILINEAR | SWS_ACCURATE_RND | SWS_FULL_CHR_H_INT : SWS_BILINEAR) {}

  void convert(const AVFrame* frame, int out_w, int out_h, uint8_t* dst);

  static std::string pixel_format_name(int format);

 private:
  int flags_;
  SwsPtr sws_;
  int src_format_ = -1, src_w_ = 0, src_h_ = 0, dst_w_ = 0, dst_h_ = 0, colorspace_ = -1, full_range_ = -1;
};

}  // namespace dojo::io::video_detail
