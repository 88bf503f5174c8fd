// VideoWriter (H.264 mp4 through libx264), write_video, and PNG output (write_png,
// write_png_frames).
#include "io/video.h"

#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <exception>
#include <filesystem>
#include <fstream>

#include "core/error.h"
#include "core/log.h"
#include "io/ffmpeg_util.h"

extern "C" {
#include <libavcodec/avcodec.h>
#include <libavformat/avformat.h>
#include <libavutil/imgutils.h>
#include <libavutil/opt.h>
#include <libswscale/swscale.h>
}

namespace dojo::io {

using namespace video_detail;

namespace {

namespace fs = std::filesystem;

// Checks a uint8 RGB tensor and returns it contiguous on the CPU.
torch::Tensor rgb_frames(const at::Tensor& tensor, int64_t rank, const std::string& what) {
  DOJO_CHECK(tensor.defined(), what + ": undefined tensor");
  DOJO_CHECK(tensor.dim() == rank && tensor.size(rank - 1) == 3,
             what + ": expected " + (rank == 3 ? "[H, W, 3]" : "[T, H, W, 3]") + " RGB, got shape " +
                 c10::str(tensor.sizes()));
  DOJO_CHECK(tensor.scalar_type() == torch::kUInt8,
             what + ": expected uint8 pixels, got " + std::string(c10::toString(tensor.scalar_type())));
  DOJO_CHECK(tensor.size(rank - 2) > 0 && tensor.size(rank - 3) > 0, what + ": empty image");
  return tensor.to(torch::kCPU).contiguous();
}

}  // namespace

// =============================================================================================
// VideoWriter

struct VideoWriter::Impl {
  std::string path;
  std::string temp_path;
  VideoWriterOptions options;
  AVFormatContext* format = nullptr;
  CodecPtr codec;
  AVStream* stream = nullptr;
  SwsPtr sws;
  FramePtr frame;
  PacketPtr packet;
  int frame_w = 0, frame_h = 0;  // input size
  int enc_w = 0, enc_h = 0;      // encoded size (even)
  int64_t written = 0;
  bool opened = false;
  bool closed = false;

  Impl(const std::string& path_, VideoWriterOptions options_) : path(path_), options(std::move(options_)) {
    init_ffmpeg();
    DOJO_CHECK(options.fps > 0, "video fps must be > 0 for '" + path + "'");
    DOJO_CHECK(options.crf >= 0 && options.crf <= 51, "x264 crf must be in [0, 51] for '" + path + "'");
    const fs::path target(path);
    temp_path = (target.parent_path() / ("." + target.filename().string() + ".tmp")).string();
  }

  ~Impl() { release(); }

  void release() {
    if (format) {
      if (format->pb) avio_closep(&format->pb);
      avformat_free_context(format);
      format = nullptr;
    }
    codec.reset();
    sws.reset();
  }

  void discard() {
    release();
    std::error_code ec;
    fs::remove(temp_path, ec);
    closed = true;
  }

  [[noreturn]] void fail(const std::string& what) {
    discard();
    throw Error("cannot write video '" + path + "': " + what);
  }

  void open(int width, int height) {
    frame_w = width;
    frame_h = height;
    enc_w = width + (width & 1);
    enc_h = height + (height & 1);
    const AVCodec* encoder = avcodec_find_encoder_by_name("libx264");
    if (!encoder) fail("this FFmpeg build has no libx264 encoder");
    const std::string dir = fs::path(path).parent_path().string();
    std::error_code ec;
    if (!dir.empty() && !fs::is_directory(dir, ec)) fail("directory '" + dir + "' does not exist");

    int ret = avformat_alloc_output_context2(&format, nullptr, "mp4", temp_path.c_str());
    if (ret < 0 || !format) fail("cannot create an mp4 muxer (" + av_error(ret) + ")");
    format->flags |= AVFMT_FLAG_BITEXACT;  // no library version strings: reproducible bytes

    codec.reset(avcodec_alloc_context3(encoder));
    if (!codec) fail("out of memory");
    const AVRational rate = av_d2q(options.fps, 1001000);
    codec->width = enc_w;
    codec->height = enc_h;
    codec->pix_fmt = AV_PIX_FMT_YUV420P;
    codec->time_base = av_inv_q(rate);
    codec->framerate = rate;
    codec->sample_aspect_ratio = AVRational{1, 1};
    codec->gop_size = options.keyframe_interval > 0 ? options.keyframe_interval
                                                    : std::max(1, static_cast<int>(std::lround(options.fps)));
    codec->thread_count = std::max(1, options.threads);
    codec->color_range = AVCOL_RANGE_MPEG;
    codec->colorspace = AVCOL_SPC_BT709;
    codec->color_primaries = AVCOL_PRI_BT709;
    codec->color_trc = AVCOL_TRC_BT709;
    if (format->oformat->flags & AVFMT_GLOBALHEADER) codec->flags |= AV_CODEC_FLAG_GLOBAL_HEADER;
    av_opt_set(codec->priv_data, "preset", options.preset.c_str(), 0);
    av_opt_set(codec->priv_data, "crf", std::to_string(options.crf).c_str(), 0);
    // x264's macroblock-tree rate control reads uninitialised memory for some frame widths
    // (e.g. 96 or 320 px), so identical input gave different bytes from one encode to the next
    // in a long-running process. Without it the output is reproducible; files are larger at the
    // same crf (+29% on a 720x528 trailer clip, which also gained 0.5 dB PSNR).
    std::string x264_params = "mbtree=0";
    if (!options.x264_params.empty()) x264_params += ":" + options.x264_params;
    av_opt_set(codec->priv_data, "x264-params", x264_params.c_str(), 0);
    ret = avcodec_open2(codec.get(), encoder, nullptr);
    if (ret < 0) fail("cannot open libx264 (" + av_error(ret) + "; preset '" + options.preset + "')");

    stream = avformat_new_stream(format, nullptr);
    if (!stream) fail("out of memory");
    ret = avcodec_parameters_from_context(stream->codecpar, codec.get());
    if (ret < 0) fail(av_error(ret));
    stream->time_base = codec->time_base;
    stream->avg_frame_rate = rate;

    ret = avio_open(&format->pb, temp_path.c_str(), AVIO_FLAG_WRITE);
    if (ret < 0) fail("cannot create '" + temp_path + "' (" + av_error(ret) + ")");
    AVDictionary* muxer_options = nullptr;
    if (options.faststart) av_dict_set(&muxer_options, "movflags", "+faststart", 0);
    ret = avformat_write_header(format, &muxer_options);
    av_dict_free(&muxer_options);
    if (ret < 0) fail("cannot write the mp4 header (" + av_error(ret) + ")");

    sws.reset(sws_getContext(enc_w, enc_h, AV_PIX_FMT_RGB24, enc_w, enc_h, AV_PIX_FMT_YUV420P,
                             SWS_BILINEAR | SWS_ACCURATE_RND | SWS_FULL_CHR_H_INP, nullptr, nullptr,
                             nullptr));
    if (!sws) fail("cannot create the RGB to YUV converter");
    sws_setColorspaceDetails(sws.get(), sws_getCoefficients(SWS_CS_ITU709), 1,
                             sws_getCoefficients(SWS_CS_ITU709), 0, 0, 1 << 16, 1 << 16);
    frame = make_frame();
    frame->format = AV_PIX_FMT_YUV420P;
    frame->width = enc_w;
    frame->height = enc_h;
    frame->color_range = AVCOL_RANGE_MPEG;
    frame->colorspace = AVCOL_SPC_BT709;
    ret = av_frame_get_buffer(frame.get(), 0);
    if (ret < 0) fail("out of memory");
    packet = make_packet();
    opened = true;
  }

  void drain(bool flushing) {
    while (true) {
      int ret = avcodec_receive_packet(codec.get(), packet.get());
      if (ret == AVERROR(EAGAIN) || ret == AVERROR_EOF) return;
      if (ret < 0) fail("encoding failed (" + av_error(ret) + ")");
      av_packet_rescale_ts(packet.get(), codec->time_base, stream->time_base);
      packet->stream_index = stream->index;
      ret = av_interleaved_write_frame(format, packet.get());
      if (ret < 0) fail("write failed (" + av_error(ret) + ")");
    }
  }

  void write(const at::Tensor& input) {
    DOJO_CHECK(!closed, "VideoWriter for '" + path + "' is already closed");
    auto rgb = rgb_frames(input, 3, "VideoWriter '" + path + "'");  // [H, W, 3] uint8
    const int h = static_cast<int>(rgb.size(0)), w = static_cast<int>(rgb.size(1));
    if (!opened) open(w, h);
    DOJO_CHECK(w == frame_w && h == frame_h, "VideoWriter '" + path + "': frame " + std::to_string(written) +
                                                 " is " + std::to_string(h) + "x" + std::to_string(w) +
                                                 " but the video is " + std::to_string(frame_h) + "x" +
                                                 std::to_string(frame_w));
    if (enc_h != h || enc_w != w) {  // repeat the last row/column up to even sizes
      if (enc_h != h) rgb = torch::cat({rgb, rgb.slice(0, h - 1, h)}, 0);
      if (enc_w != w) rgb = torch::cat({rgb, rgb.slice(1, w - 1, w)}, 1);
      rgb = rgb.contiguous();
    }
    int ret = av_frame_make_writable(frame.get());
    if (ret < 0) fail("out of memory");
    const uint8_t* src_planes[4] = {rgb.data_ptr<uint8_t>(), nullptr, nullptr, nullptr};
    const int src_strides[4] = {enc_w * 3, 0, 0, 0};
    sws_scale(sws.get(), src_planes, src_strides, 0, enc_h, frame->data, frame->linesize);
    frame->pts = written;
    ret = avcodec_send_frame(codec.get(), frame.get());
    if (ret < 0) fail("encoding failed (" + av_error(ret) + ")");
    ++written;
    drain(false);
  }

  void close() {
    if (closed) return;
    if (!opened) {
      discard();
      throw Error("cannot write video '" + path + "': no frames were written");
    }
    int ret = avcodec_send_frame(codec.get(), nullptr);
    if (ret < 0) fail("flushing the encoder failed (" + av_error(ret) + ")");
    drain(true);
    ret = av_write_trailer(format);
    if (ret < 0) fail("cannot finish the mp4 file (" + av_error(ret) + ")");
    ret = avio_closep(&format->pb);
    if (ret < 0) fail("cannot close '" + temp_path + "' (" + av_error(ret) + ")");
    release();
    std::error_code ec;
    fs::rename(temp_path, path, ec);
    if (ec) {
      fs::remove(temp_path, ec);
      closed = true;
      throw Error("cannot move the finished video onto '" + path + "': " + ec.message());
    }
    closed = true;
  }
};

VideoWriter::VideoWriter(const std::string& path, VideoWriterOptions options)
    : impl_(std::make_unique<Impl>(path, std::move(options))) {}

VideoWriter::~VideoWriter() {
  if (!impl_ || impl_->closed) return;
  if (std::uncaught_exceptions() > 0) {
    impl_->discard();
    return;
  }
  try {
    impl_->close();
  } catch (const std::exception& e) {
    LOG_ERROR(e.what());
  }
}

void VideoWriter::write(const at::Tensor& frame) { impl_->write(frame); }

void VideoWriter::write_many(const at::Tensor& frames) {
  auto batch = rgb_frames(frames, 4, "VideoWriter '" + impl_->path + "'");  // [T, H, W, 3] uint8
  for (int64_t t = 0; t < batch.size(0); ++t) impl_->write(batch[t]);
}

void VideoWriter::close() { impl_->close(); }
int64_t VideoWriter::frames_written() const { return impl_->written; }
const std::string& VideoWriter::path() const { return impl_->path; }

void write_video(const std::string& path, const at::Tensor& frames, const VideoWriterOptions& options) {
  VideoWriter writer(path, options);
  writer.write_many(frames);
  writer.close();
}

// =============================================================================================
// PNG

void write_png(const std::string& path, const at::Tensor& image) {
  init_ffmpeg();
  auto rgb = rgb_frames(image, 3, "write_png '" + path + "'");  // [H, W, 3] uint8
  const int h = static_cast<int>(rgb.size(0)), w = static_cast<int>(rgb.size(1));
  const AVCodec* encoder = avcodec_find_encoder(AV_CODEC_ID_PNG);
  if (!encoder) throw Error("cannot write '" + path + "': this FFmpeg build has no PNG encoder");
  CodecPtr codec(avcodec_alloc_context3(encoder));
  if (!codec) throw Error("out of memory writing '" + path + "'");
  codec->width = w;
  codec->height = h;
  codec->pix_fmt = AV_PIX_FMT_RGB24;
  codec->time_base = AVRational{1, 1};
  int ret = avcodec_open2(codec.get(), encoder, nullptr);
  if (ret < 0) throw Error("cannot write '" + path + "': PNG encoder failed to open (" + av_error(ret) + ")");
  FramePtr frame = make_frame();
  frame->format = AV_PIX_FMT_RGB24;
  frame->width = w;
  frame->height = h;
  // The frame borrows the tensor's pixels; the encoder copies what it needs.
  av_image_fill_arrays(frame->data, frame->linesize, rgb.data_ptr<uint8_t>(), AV_PIX_FMT_RGB24, w, h, 1);
  frame->pts = 0;
  PacketPtr packet = make_packet();
  ret = avcodec_send_frame(codec.get(), frame.get());
  if (ret >= 0) ret = avcodec_send_frame(codec.get(), nullptr);
  if (ret >= 0) ret = avcodec_receive_packet(codec.get(), packet.get());
  if (ret < 0) throw Error("cannot write '" + path + "': PNG encoding failed (" + av_error(ret) + ")");
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) throw Error("cannot create '" + path + "'");
  out.write(reinterpret_cast<const char*>(packet->data), packet->size);
  if (!out) throw Error("write failed for '" + path + "'");
}

std::vector<std::string> write_png_frames(const std::string& dir, const at::Tensor& frames,
                                          const std::string& prefix, int64_t first_index) {
  auto batch = as_batch(frames, "write_png_frames");  // [T, H, W, 3]
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (!fs::is_directory(dir)) throw Error("cannot create directory '" + dir + "'");
  std::vector<std::string> paths;
  for (int64_t t = 0; t < batch.size(0); ++t) {
    char name[32];
    std::snprintf(name, sizeof(name), "%06lld.png", static_cast<long long>(first_index + t));
    paths.push_back((fs::path(dir) / (prefix + name)).string());
    write_png(paths.back(), batch[t]);
  }
  return paths;
}

}  // namespace dojo::io
