// Video I/O on FFmpeg (libavformat/libavcodec/libswscale): decode any container/codec FFmpeg
// knows (mp4/mkv/webm/avi/mov with H.264, HEVC, VP9, AV1, MPEG-4, ...) to RGB uint8 tensors
// with frame-accurate random access; encode H.264 mp4 and PNG; crop/resize transforms; labelled
// side-by-side comparison videos. FFmpeg headers stay in the .cpp files (and the internal
// ffmpeg_util.h).
//
// Frame indices. Frame i is the i-th picture a full sequential decode outputs (presentation
// order, from 0); `ffmpeg -vf select=eq(n\,i)` picks the same picture. The frame count is the
// number of video packets that carry a picture (not empty AVI dropped-frame placeholders, not
// packets an mp4 edit list cuts, not a truncated last packet). It is computed once per reader
// by demuxing the whole file (no decoding; ~3 ms for the 8 MB vtest.avi). The header's
// nb_frames is not used: AVI headers count dropped-frame placeholders (tree.avi says 444, 68
// pictures exist), mkv/webm have none. FFmpeg's own log output goes to LOG_DEBUG (-v).
#pragma once

#include <ATen/core/Tensor.h>

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

#include "io/frame_ops.h"

namespace dojo::io {

// ---------------------------------------------------------------------------------------------
// Reading

struct VideoReaderOptions {
  // Decoder threads (FFmpeg frame + slice threading). 0 lets FFmpeg pick from the core count.
  int threads = 0;
  // YUV -> RGB: false (default) interpolates chroma and rounds exactly, identical to
  // `ffmpeg -sws_flags bilinear+accurate_rnd+full_chroma_int -pix_fmt rgb24`. true uses
  // swscale's fast path (nearest chroma, colours 1-2 levels darker), ~3x faster conversion.
  bool fast_color = false;
};

struct VideoInfo {
  std::string path;
  int64_t frames = 0;  // pictures a full decode yields (see the rule at the top)
  int width = 0;       // stored size; sample aspect ratio and rotation tags are ignored
  int height = 0;
  double fps = 0;            // nominal rate of the stream (FFmpeg's guess: r_frame_rate/avg)
  std::string codec;         // FFmpeg codec name: h264, hevc, vp9, av1, mpeg4, msmpeg4v3, ...
  std::string container;     // demuxer name: "avi", "mov,mp4,m4a,3gp,3g2,mj2", "matroska,webm"
  double duration_s = 0;     // stream duration, else container duration, else frames / fps
  std::string pixel_format;  // decoder output format before RGB conversion, e.g. yuv420p
  int64_t keyframes = 0;     // keyframe packets; random access decodes from the one before

  // {path, frames, width, height, fps, codec, container, duration_s, pixel_format, keyframes}
  nlohmann::json to_json() const;
};

// Opens a video file and decodes frames by index. Not thread-safe: use one reader per thread.
// Errors (missing file, not a video, no video stream, unsupported codec, corrupt or truncated
// data, index out of range) throw dojo::Error naming the file (and the index).
//
// Random access: to reach frame i the reader seeks to the last keyframe at or before i and
// decodes forward, converting only the requested frames to RGB. Sorted requests are served in
// one forward pass; it seeks only when a keyframe lets it skip decoding at least 8 frames. A
// decoded picture is matched to its index
//  - by its pts (rank among all packet pts), when every packet has a distinct pts: mp4, mkv,
//    webm, mov, B-frame-free AVI;
//  - else by the packet it came from, for MPEG-4 part 2 and MPEG-1/2 (AVI with B-frames has no
//    pts): the decoder is fed pts = packet number, and the presentation order of packets is
//    derived from their picture types (B shown at once, I/P when the next I/P arrives; DivX
//    "packed B-frames" replayed like libavcodec does), and for codecs without reordering;
//  - else by counting frames from the start (no seeking; correct, slow for late frames).
// If a seek lands after the frame (damaged data, leading pictures) it retries from earlier
// keyframes, finally from the start, so results equal a sequential decode (tested, and
// bit-identical to the ffmpeg CLI with the same scaler flags).
class VideoReader {
 public:
  explicit VideoReader(const std::string& path, VideoReaderOptions options = {});
  ~VideoReader();
  VideoReader(VideoReader&&) noexcept;
  VideoReader& operator=(VideoReader&&) noexcept;
  VideoReader(const VideoReader&) = delete;
  VideoReader& operator=(const VideoReader&) = delete;

  const VideoInfo& info() const;
  int64_t num_frames() const;
  const std::string& path() const;

  at::Tensor read_frame(int64_t index);  // [H, W, 3] uint8 RGB
  // Frames in the order given (duplicates allowed), decoded in ascending order.
  at::Tensor read_frames(const std::vector<int64_t>& indices);  // [T, H, W, 3] uint8
  // Frames start, start + stride, ...: `count` of them, or all that exist when count < 0.
  at::Tensor read_range(int64_t start, int64_t count, int64_t stride = 1);  // [T, H, W, 3] uint8
  at::Tensor read_all();                                                    // [N, H, W, 3] uint8

  // Streams the frames read_range(start, count, stride) would return to fn(index, frame) without
  // holding them all; `frame` ([H, W, 3] uint8) is reused between calls, clone it to keep it.
  void for_each_frame(int64_t start, int64_t count, int64_t stride,
                      const std::function<void(int64_t index, const at::Tensor& frame)>& fn);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

VideoInfo probe_video(const std::string& path);

// Frames per second of a full sequential decode to RGB (what data loading pays), the median
// over `repeats` passes; opening the file and building the index are not timed. max_frames < 0
// decodes the whole file. For `dojo bench`.
double measure_decode_fps(const std::string& path, int repeats = 3, VideoReaderOptions options = {},
                          int64_t max_frames = -1);

// ---------------------------------------------------------------------------------------------
// Transforms on frames (center_crop, center_crop_aspect, resize, ...): io/frame_ops.h, included above.

// ---------------------------------------------------------------------------------------------
// Writing

struct VideoWriterOptions {
  double fps = 30.0;              // stored as a rational (29.97 -> 2997/100, 30000/1001 stays)
  int crf = 18;                   // x264 constant rate factor: 0 lossless luma, 18 near-transparent
  std::string preset = "medium";  // x264 speed/size trade-off: ultrafast ... veryslow
  int keyframe_interval = 0;      // frames between keyframes; 0 = one per second (cheap seeking)
  // x264 threads. Fixed (not "all cores") so identical input gives byte-identical files on
  // every machine; the data pipeline relies on that.
  int threads = 1;
  bool faststart = true;  // index (moov) at the front so browsers can play while downloading
  // Extra x264 options "key=value:key=value" after the default "mbtree=0", which keeps output
  // byte-reproducible (x264's mbtree reads uninitialised memory at some widths); "mbtree=1"
  // gives smaller files that may differ between runs.
  std::string x264_params;
};

// H.264 (libx264) in mp4, yuv420p, BT.709 limited range, tagged so browsers render it right.
// The size is taken from the first frame; odd widths/heights are padded by repeating the last
// column/row (yuv420p needs even sizes), so the file can be one pixel larger than the frames.
// Frames go to "<path>.tmp" and close() renames it onto path, so path never holds a partial
// video. Destroying an unclosed writer closes it, unless an exception is unwinding, in which
// case the temporary file is deleted.
class VideoWriter {
 public:
  explicit VideoWriter(const std::string& path, VideoWriterOptions options = {});
  ~VideoWriter();
  VideoWriter(const VideoWriter&) = delete;
  VideoWriter& operator=(const VideoWriter&) = delete;

  void write(const at::Tensor& frame);        // [H, W, 3] uint8 RGB
  void write_many(const at::Tensor& frames);  // [T, H, W, 3] uint8 RGB
  // Flushes the encoder, finishes the file and moves it into place. Throws if no frame was
  // written. Idempotent.
  void close();

  int64_t frames_written() const;
  const std::string& path() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// One-shot helper: [T, H, W, 3] uint8 -> H.264 mp4.
void write_video(const std::string& path, const at::Tensor& frames, const VideoWriterOptions& options = {});

// PNG (libavcodec's encoder, RGB24, lossless). write_png_frames writes
// dir/<prefix><index, 6 digits>.png for index = first_index + i and returns the paths; it
// creates dir when missing.
void write_png(const std::string& path, const at::Tensor& frame);  // [H, W, 3] uint8
std::vector<std::string> write_png_frames(const std::string& dir, const at::Tensor& frames,
                                          const std::string& prefix = "frame_", int64_t first_index = 0);

// ---------------------------------------------------------------------------------------------
// Comparison videos and text

// Draws ASCII text with the built-in 5x7 font, each font pixel a scale x scale block; glyph
// cells are 6 x 8 font pixels (one blank column/row of spacing). (x, y) is the top-left corner;
// pixels outside the image are clipped; non-ASCII characters draw as '?'.
void draw_text(at::Tensor& image, const std::string& text, int64_t x, int64_t y, int scale = 1,
               std::array<uint8_t, 3> color = {255, 255, 255});  // image [H, W, 3] uint8
// Width and height in pixels of draw_text's output for `text` at `scale`.
std::array<int64_t, 2> text_size(const std::string& text, int scale = 1);

// Nearest-neighbour enlargement of frames [T, H, W, 3] by an integer factor (crisp pixels, so a
// small render can be looked at): [T, H * factor, W * factor, 3].
at::Tensor upscale_nearest(const at::Tensor& frames, int64_t factor);
// Draws a small cross (arms of `radius` pixels) at each point onto frames [T, H, W, 3] in place:
// points [T, K, 2] as (u, v) in [0, 1] over the frame, drawn where show [T, K] is true, in the
// colour of the point's index (colors cycle).
void draw_markers(at::Tensor& frames, const at::Tensor& points, const at::Tensor& show, int64_t radius,
                  const std::vector<std::array<uint8_t, 3>>& colors);

// Places the videos side by side on a black canvas with a label strip above each panel (label
// centred, truncated to the panel width). Panels keep their size and are top-aligned; shorter
// videos hold their last frame; a 4-pixel gap separates panels; the canvas is padded to even
// width/height. labels may be empty (no strip) or have one entry per video.
at::Tensor compose_side_by_side(const std::vector<at::Tensor>& videos,    // each [T_i, H_i, W_i, 3]
                                const std::vector<std::string>& labels);  // -> [max T, H', W', 3]
void write_comparison_video(const std::string& path, const std::vector<at::Tensor>& videos,
                            const std::vector<std::string>& labels, double fps,
                            VideoWriterOptions options = {});

}  // namespace dojo::io
