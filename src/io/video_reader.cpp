// VideoReader: frame-accurate random access to any video FFmpeg decodes (index built by
// demuxing, seeking, decoding, RGB conversion), probe_video and measure_decode_fps.
#include "io/video.h"

#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <functional>
#include <nlohmann/json.hpp>
#include <numeric>
#include <unordered_map>

#include "core/error.h"
#include "core/log.h"
#include "io/ffmpeg_util.h"

extern "C" {
#include <libavcodec/avcodec.h>
#include <libavformat/avformat.h>
}

namespace dojo::io {

using namespace video_detail;

namespace {

namespace fs = std::filesystem;

// Decoding forward is preferred over a seek unless the seek skips at least this many frames:
// a seek flushes the (frame-threaded) decoder, which costs a few frames of latency itself.
constexpr int64_t kMinFramesSkippedBySeek = 8;

}  // namespace

// =============================================================================================
// VideoReader

struct VideoReader::Impl {
  // One video packet as the demuxer delivered it.
  struct Entry {
    int64_t pts, dts, pos;
    bool key;
  };
  // A place decoding can start from: rewinding (ordinal 0) or a keyframe.
  struct SeekPoint {
    int64_t ordinal;
    int64_t entry;  // index into entries_ (decode order), -1 = rewind to the start
  };

  std::string path;
  VideoReaderOptions options;
  VideoInfo info;

  FormatInputPtr format;
  CodecPtr codec;
  int stream_index = -1;
  AVRational time_base{0, 1};
  PacketPtr packet;
  FramePtr frame;
  RgbConverter converter;

  // How decoded frames are matched to frame indices.
  enum class Mode {
    kTimestamp,    // every packet has a distinct pts: index = rank of the frame's pts
    kPacketOrder,  // no pts, but the reordering is known: the decoder is fed pts = decode
                   // position and index = packet_ordinal[that position]
    kCount,        // neither: decode from the start and count output frames (no seeking)
  };

  // Index built once by demuxing the whole file.
  std::vector<Entry> entries;  // decode order
  Mode mode = Mode::kTimestamp;
  std::vector<int64_t> sorted_pts;                    // kTimestamp: ordinal -> pts
  std::vector<int64_t> packet_ordinal;                // kPacketOrder: decode position -> ordinal
  std::unordered_map<int64_t, int64_t> entry_by_pos;  // byte position -> decode position
  std::vector<SeekPoint> seek_points;                 // ascending ordinals, first is the rewind

  // Decoder position.
  bool position_known = false;  // false after errors: the next read seeks
  int64_t last_ordinal = -1;    // ordinal of the last frame output; -1 = none since seek/rewind
  int64_t next_count = 0;       // kCount: ordinal of the next frame to come out
  bool demux_eof = false;
  bool decoder_eof = false;
  PacketPtr pending;  // a packet read while validating a seek, sent before reading more
  bool has_pending = false;

  Impl(const std::string& path_, VideoReaderOptions options_)
      : path(path_), options(options_), converter(!options_.fast_color) {
    init_ffmpeg();
    std::error_code ec;
    if (!fs::exists(path, ec)) throw Error("video file not found: '" + path + "'");
    if (fs::is_directory(path, ec)) throw Error("expected a video file, got a directory: '" + path + "'");
    packet = make_packet();
    pending = make_packet();
    frame = make_frame();
    open_input();
    open_decoder();
    build_index();
    fill_info();
    rewind();
  }

  [[noreturn]] void fail(const std::string& what) const { throw Error(what + " in '" + path + "'"); }

  void open_input() {
    AVFormatContext* raw = nullptr;
    int ret = avformat_open_input(&raw, path.c_str(), nullptr, nullptr);
    if (ret < 0) throw Error("cannot open video '" + path + "': " + av_error(ret));
    format.reset(raw);
    // FFmpeg's ANSI-art demuxer accepts any text file as a "video".
    if (std::string(format->iformat->name) == "tty") throw Error("not a video file: '" + path + "'");
    ret = avformat_find_stream_info(format.get(), nullptr);
    if (ret < 0) throw Error("cannot read stream info of '" + path + "': " + av_error(ret));
    const int best = av_find_best_stream(format.get(), AVMEDIA_TYPE_VIDEO, -1, -1, nullptr, 0);
    if (best < 0) throw Error("no video stream in '" + path + "'");
    if (stream_index >= 0 && best != stream_index) fail("video stream changed on reopening");
    stream_index = best;
    AVStream* stream = format->streams[stream_index];
    time_base = stream->time_base;
    for (unsigned i = 0; i < format->nb_streams; ++i)
      format->streams[i]->discard = static_cast<int>(i) == stream_index ? AVDISCARD_DEFAULT : AVDISCARD_ALL;
  }

  void open_decoder() {
    const AVCodecParameters* par = format->streams[stream_index]->codecpar;
    const AVCodec* decoder = avcodec_find_decoder(par->codec_id);
    if (!decoder) fail(std::string("no decoder for codec ") + avcodec_get_name(par->codec_id));
    codec.reset(avcodec_alloc_context3(decoder));
    if (!codec) throw Error("out of memory opening the decoder for '" + path + "'");
    int ret = avcodec_parameters_to_context(codec.get(), par);
    if (ret < 0) fail("bad codec parameters (" + av_error(ret) + ")");
    codec->thread_count = std::max(0, options.threads);
    codec->thread_type = FF_THREAD_FRAME | FF_THREAD_SLICE;
    codec->pkt_timebase = time_base;
    ret = avcodec_open2(codec.get(), decoder, nullptr);
    if (ret < 0) fail(std::string("cannot open the ") + decoder->name + " decoder (" + av_error(ret) + ")");
    if (par->width <= 0 || par->height <= 0) fail("video stream has no frame size");
  }

  // Demuxes every packet of the video stream once: frame count, timestamps, keyframes.
  void build_index() {
    const AVCodecID codec_id = format->streams[stream_index]->codecpar->codec_id;
    std::vector<std::vector<Picture>> pictures;  // per packet, for streams without pts
    std::vector<int> sizes;
    while (true) {
      const int ret = av_read_frame(format.get(), packet.get());
      if (ret < 0) {
        if (ret != AVERROR_EOF) LOG_DEBUG("index of ", path, " stops early: ", av_error(ret));
        break;
      }
      if (packet->stream_index == stream_index && is_frame_packet(packet.get())) {
        entry_by_pos.emplace(packet->pos, static_cast<int64_t>(entries.size()));
        entries.push_back({packet->pts, packet->dts, packet->pos, (packet->flags & AV_PKT_FLAG_KEY) != 0});
        pictures.push_back(pictures_in(codec_id, packet->data, packet->size));
        sizes.push_back(packet->size);
      }
      av_packet_unref(packet.get());
    }
    if (entries.empty()) fail("no video frames (empty, truncated or corrupt file)");

    bool all_pts = true;
    for (const auto& e : entries) {
      if (e.pts == AV_NOPTS_VALUE) all_pts = false;
      sorted_pts.push_back(e.pts);
    }
    std::sort(sorted_pts.begin(), sorted_pts.end());
    if (all_pts && std::adjacent_find(sorted_pts.begin(), sorted_pts.end()) == sorted_pts.end()) {
      mode = Mode::kTimestamp;
    } else {
      sorted_pts.clear();
      packet_ordinal = presentation_order(codec_id, decoded_picture_types(codec_id, pictures, sizes));
      mode = packet_ordinal.empty() ? Mode::kCount : Mode::kPacketOrder;
    }
    // Without pts a seek is recognised by the byte position it lands on.
    if (mode != Mode::kTimestamp && entry_by_pos.size() != entries.size()) mode = Mode::kCount;

    seek_points.push_back({0, -1});
    for (size_t i = 0; mode != Mode::kCount && i < entries.size(); ++i) {
      const Entry& e = entries[i];
      if (!e.key || (e.dts == AV_NOPTS_VALUE && e.pts == AV_NOPTS_VALUE)) continue;
      const int64_t ordinal = mode == Mode::kTimestamp ? ordinal_of_pts(e.pts) : packet_ordinal[i];
      if (ordinal > 0) seek_points.push_back({ordinal, static_cast<int64_t>(i)});
    }
    std::sort(seek_points.begin(), seek_points.end(),
              [](const SeekPoint& a, const SeekPoint& b) { return a.ordinal < b.ordinal; });
    static const char* mode_names[] = {"timestamp", "packet-order", "count"};
    LOG_DEBUG("indexed ", path, ": ", entries.size(), " frames, ", seek_points.size() - 1, " seek points, ",
              mode_names[static_cast<int>(mode)], " mode");
  }

  // A picture header inside a packet: coding type ('I', 'P', 'B' or '?') and byte offset.
  struct Picture {
    char type;
    int offset;
  };

  // The pictures in one packet, for the codecs whose reordering presentation_order() models:
  // MPEG-4 part 2 (VOP headers) and MPEG-1/2 (picture headers). Empty for other codecs.
  static std::vector<Picture> pictures_in(AVCodecID codec_id, const uint8_t* data, int size) {
    std::vector<Picture> found;
    const bool mpeg4 = codec_id == AV_CODEC_ID_MPEG4;
    const bool mpeg12 = codec_id == AV_CODEC_ID_MPEG1VIDEO || codec_id == AV_CODEC_ID_MPEG2VIDEO;
    if (!mpeg4 && !mpeg12) return found;
    for (int i = 0; i + 5 < size; ++i) {
      if (data[i] != 0 || data[i + 1] != 0 || data[i + 2] != 1) continue;
      if (mpeg4 && data[i + 3] == 0xB6) {
        found.push_back({"IPBP"[data[i + 4] >> 6], i});  // vop_coding_type; S (GMC) is an anchor
      } else if (mpeg12 && data[i + 3] == 0x00) {
        const int type = (data[i + 5] >> 3) & 7;  // after the 10-bit temporal_reference
        found.push_back({type == 1 ? 'I' : type == 2 ? 'P' : type == 3 ? 'B' : '?', i});
      }
    }
    return found;
  }

  // The type of the picture the decoder outputs for each packet. Usually the packet's first
  // picture, but MPEG-4 "packed B-frames" (DivX/Xvid in AVI: [P B] [B] [N-VOP]) make FFmpeg's
  // decoder keep the rest of a packet, from the first I/B VOP after the decoded one, and decode
  // that in place of the next packet. This replays that rule (libavcodec h263dec/mpeg4videodec).
  static std::vector<char> decoded_picture_types(AVCodecID codec_id,
                                                 const std::vector<std::vector<Picture>>& pictures,
                                                 const std::vector<int>& sizes) {
    std::vector<char> types(pictures.size(), '?');
    const bool packed =
        codec_id == AV_CODEC_ID_MPEG4 &&
        std::any_of(pictures.begin(), pictures.end(), [](const auto& p) { return p.size() > 1; });
    char stored = 0;  // first picture of the kept bitstream, 0 = none
    for (size_t i = 0; i < pictures.size(); ++i) {
      const auto& here = pictures[i];
      bool from_stored = false;
      if (stored && packed) {
        types[i] = stored;
        from_stored = true;
      } else if (!here.empty()) {
        types[i] = here.front().type;
      }
      stored = 0;
      if (!packed || here.empty()) continue;
      // Search from the start of this packet when the kept bitstream was decoded, else after the
      // picture just decoded; the first VOP found is kept if it is an I or B picture.
      const int from = from_stored ? 0 : here.front().offset + 1;
      if (sizes[i] - from <= 7) continue;
      for (const auto& p : here) {
        if (p.offset < from) continue;
        if (p.type == 'I' || p.type == 'B') stored = p.type;
        break;
      }
    }
    return types;
  }

  // Presentation index of every packet (decode order) for streams without timestamps, or empty
  // when unknown. No reordering: identity. MPEG-4 part 2 / MPEG-1/2: B-pictures are shown at
  // once, each I/P picture when the next I/P picture is decoded (or at the end).
  std::vector<int64_t> presentation_order(AVCodecID codec_id, const std::vector<char>& types) const {
    const int64_t n = static_cast<int64_t>(types.size());
    std::vector<int64_t> ordinal(n);
    const bool modelled = codec_id == AV_CODEC_ID_MPEG4 || codec_id == AV_CODEC_ID_MPEG1VIDEO ||
                          codec_id == AV_CODEC_ID_MPEG2VIDEO;
    if (!modelled) {
      if (format->streams[stream_index]->codecpar->video_delay != 0) return {};
      std::iota(ordinal.begin(), ordinal.end(), 0);
      return ordinal;
    }
    if (std::find(types.begin(), types.end(), '?') != types.end()) return {};
    int64_t next = 0, pending = -1;
    for (int64_t i = 0; i < n; ++i) {
      if (types[i] == 'B') {
        ordinal[i] = next++;
        continue;
      }
      if (pending >= 0) ordinal[pending] = next++;
      pending = i;
    }
    if (pending >= 0) ordinal[pending] = next++;
    return ordinal;
  }

  int64_t ordinal_of_pts(int64_t pts) const {
    const auto it = std::lower_bound(sorted_pts.begin(), sorted_pts.end(), pts);
    if (it == sorted_pts.end() || *it != pts) return -1;
    return it - sorted_pts.begin();
  }

  void fill_info() {
    const AVStream* stream = format->streams[stream_index];
    info.path = path;
    info.frames = static_cast<int64_t>(entries.size());
    info.width = stream->codecpar->width;
    info.height = stream->codecpar->height;
    const AVRational rate = av_guess_frame_rate(format.get(), const_cast<AVStream*>(stream), nullptr);
    info.fps = (rate.num > 0 && rate.den > 0) ? av_q2d(rate) : 0.0;
    info.codec = avcodec_get_name(stream->codecpar->codec_id);
    info.container = format->iformat->name;
    if (stream->duration != AV_NOPTS_VALUE && stream->duration > 0)
      info.duration_s = static_cast<double>(stream->duration) * av_q2d(stream->time_base);
    else if (format->duration != AV_NOPTS_VALUE && format->duration > 0)
      info.duration_s = static_cast<double>(format->duration) / AV_TIME_BASE;
    else if (info.fps > 0)
      info.duration_s = static_cast<double>(info.frames) / info.fps;
    const int pix = stream->codecpar->format >= 0 ? stream->codecpar->format : codec->pix_fmt;
    info.pixel_format = RgbConverter::pixel_format_name(pix);
    info.keyframes = std::count_if(entries.begin(), entries.end(), [](const Entry& e) { return e.key; });
  }

  // --- positioning ---------------------------------------------------------------------------

  void reset_decoder_state() {
    avcodec_flush_buffers(codec.get());
    demux_eof = false;
    decoder_eof = false;
    has_pending = false;
    av_packet_unref(pending.get());
    last_ordinal = -1;
    position_known = true;
  }

  // Packets the decoder gets. Empty ones are AVI dropped-frame placeholders; a short read (the
  // last packet of a truncated file) is flagged corrupt and could not be decoded anyway.
  static bool is_decodable_packet(const AVPacket* p) {
    return p->size > 0 && !(p->flags & AV_PKT_FLAG_CORRUPT);
  }
  // Packets that are frames: decodable ones except those an edit list cuts away (the decoder
  // still needs them as references but drops their pictures).
  static bool is_frame_packet(const AVPacket* p) {
    return is_decodable_packet(p) && !(p->flags & AV_PKT_FLAG_DISCARD);
  }

  // Reads the next frame packet of the video stream into `out`; false at end of file or on a
  // read error (a truncated file simply ends there).
  bool read_video_packet(AVPacket* out) {
    while (true) {
      const int ret = av_read_frame(format.get(), out);
      if (ret < 0) {
        if (ret != AVERROR_EOF) LOG_DEBUG("read error in ", path, ": ", av_error(ret));
        return false;
      }
      if (out->stream_index == stream_index && is_decodable_packet(out)) return true;
      av_packet_unref(out);
    }
  }

  // Back to the first frame. Seeking to the first packet is verified by its byte position;
  // formats that cannot do it are reopened.
  void rewind() {
    bool ok = false;
    const Entry& first = entries.front();
    const int64_t ts = first.dts != AV_NOPTS_VALUE ? first.dts : first.pts;
    if (ts != AV_NOPTS_VALUE && av_seek_frame(format.get(), stream_index, ts, AVSEEK_FLAG_BACKWARD) >= 0) {
      reset_decoder_state();
      if (read_video_packet(pending.get())) {
        has_pending = true;
        ok = first.pos < 0 || pending->pos == first.pos;
      }
    }
    if (!ok) {
      LOG_DEBUG("reopening ", path, " to rewind");
      format.reset();
      open_input();
      reset_decoder_state();
    }
    next_count = 0;
  }

  // Seeks so that decoding continues at seek point `sp`; falls back to rewinding when the
  // demuxer lands elsewhere than the keyframe asked for.
  void seek_to(const SeekPoint& sp) {
    if (sp.entry < 0) return rewind();
    const Entry& key = entries[sp.entry];
    const int64_t ts = key.dts != AV_NOPTS_VALUE ? key.dts : key.pts;
    if (av_seek_frame(format.get(), stream_index, ts, AVSEEK_FLAG_BACKWARD) < 0) return rewind();
    reset_decoder_state();
    if (!read_video_packet(pending.get())) return rewind();
    has_pending = true;
    if (mode == Mode::kTimestamp) return;  // frames identify themselves by pts
    // The first packet must be a keyframe whose decode position we know.
    const auto it = entry_by_pos.find(pending->pos);
    if (it == entry_by_pos.end() || !entries[it->second].key) return rewind();
  }

  // --- decoding ------------------------------------------------------------------------------

  // Decodes the next frame into `frame`; returns its ordinal, -1 for a frame that cannot be
  // placed (skip it), or -2 at the end of the stream.
  int64_t decode_next() {
    int errors = 0;
    while (true) {
      int ret = avcodec_receive_frame(codec.get(), frame.get());
      if (ret == 0) return place_frame();
      if (ret == AVERROR_EOF) {
        decoder_eof = true;
        return -2;
      }
      if (ret != AVERROR(EAGAIN)) {
        LOG_DEBUG("decode error in ", path, ": ", av_error(ret));
        if (demux_eof || ++errors > 1000) {
          decoder_eof = true;
          return -2;
        }
        continue;
      }
      if (demux_eof) {  // drained after the flush packet yet no EOF: treat as the end
        decoder_eof = true;
        return -2;
      }
      AVPacket* pkt = nullptr;
      if (has_pending) {
        has_pending = false;
        av_packet_move_ref(packet.get(), pending.get());
        pkt = packet.get();
      } else if (read_video_packet(packet.get())) {
        pkt = packet.get();
      } else {
        demux_eof = true;  // send the flush packet to drain delayed frames
      }
      if (pkt && mode == Mode::kPacketOrder) {
        // Decoders hand each frame the pts of the packet that carried its picture.
        const auto it = entry_by_pos.find(pkt->pos);
        pkt->pts = it != entry_by_pos.end() ? it->second : AV_NOPTS_VALUE;
      }
      ret = avcodec_send_packet(codec.get(), pkt);
      if (pkt) av_packet_unref(pkt);
      if (ret < 0 && ret != AVERROR(EAGAIN) && ret != AVERROR_EOF)
        LOG_DEBUG("corrupt packet in ", path, ": ", av_error(ret));
    }
  }

  int64_t place_frame() {
    int64_t ordinal = -1;
    if (mode == Mode::kTimestamp) {
      const int64_t ts = frame->pts != AV_NOPTS_VALUE ? frame->pts : frame->best_effort_timestamp;
      if (ts != AV_NOPTS_VALUE) ordinal = ordinal_of_pts(ts);
    } else if (mode == Mode::kPacketOrder) {
      if (frame->pts >= 0 && frame->pts < static_cast<int64_t>(packet_ordinal.size()))
        ordinal = packet_ordinal[frame->pts];
    } else {
      ordinal = next_count++;
    }
    if (ordinal < 0 && last_ordinal >= 0) ordinal = last_ordinal + 1;
    if (ordinal >= 0) last_ordinal = ordinal;
    return ordinal;
  }

  // The seek point to start from for `target`, counting back `back` extra points.
  const SeekPoint& seek_point_for(int64_t target, size_t back) const {
    auto it = std::upper_bound(seek_points.begin(), seek_points.end(), target,
                               [](int64_t t, const SeekPoint& sp) { return t < sp.ordinal; });
    size_t i = static_cast<size_t>(it - seek_points.begin()) - 1;  // seek_points[0].ordinal == 0
    i = i > back ? i - back : 0;
    return seek_points[i];
  }

  // Leaves `frame` holding frame `target`.
  void decode_to(int64_t target) {
    const SeekPoint& nearest = seek_point_for(target, 0);
    bool seeked = !(position_known && !decoder_eof && target > last_ordinal &&
                    nearest.ordinal - (last_ordinal + 1) < kMinFramesSkippedBySeek);
    if (seeked) seek_to(nearest);
    // A keyframe seek can land after the target (leading pictures, damaged data): retry from
    // earlier seek points, finally from the start, before calling the frame undecodable.
    size_t back = 0;
    while (true) {
      int64_t ordinal;
      do {
        ordinal = decode_next();
      } while (ordinal == -1 || (ordinal >= 0 && ordinal < target));
      if (ordinal == target) return;
      if (!seeked) {
        seeked = true;
      } else if (seek_point_for(target, back).entry < 0) {
        position_known = false;
        throw Error("cannot decode frame " + std::to_string(target) + " of '" + path +
                    "' (corrupt or truncated data)");
      } else {
        ++back;
      }
      LOG_DEBUG("frame ", target, " of ", path, " missed; decoding again from an earlier seek point");
      seek_to(seek_point_for(target, back));
    }
  }

  void check_index(int64_t index) const {
    if (index < 0 || index >= info.frames)
      throw Error("frame index " + std::to_string(index) + " out of range for '" + path + "' (" +
                  std::to_string(info.frames) + " frames)");
  }

  void convert_current(uint8_t* dst) { converter.convert(frame.get(), info.width, info.height, dst); }

  torch::Tensor read_sorted(const std::vector<int64_t>& indices) {
    for (int64_t index : indices) check_index(index);
    std::vector<size_t> order(indices.size());
    std::iota(order.begin(), order.end(), 0);
    std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return indices[a] < indices[b]; });
    auto out = torch::empty({static_cast<int64_t>(indices.size()), info.height, info.width, 3},
                            torch::kUInt8);  // [T, H, W, 3] uint8
    const int64_t frame_bytes = static_cast<int64_t>(info.height) * info.width * 3;
    uint8_t* base = out.data_ptr<uint8_t>();
    for (size_t k = 0; k < order.size(); ++k) {
      const size_t slot = order[k];
      if (k > 0 && indices[order[k - 1]] == indices[slot]) {
        std::memcpy(base + slot * frame_bytes, base + order[k - 1] * frame_bytes, frame_bytes);
        continue;
      }
      try {
        decode_to(indices[slot]);
      } catch (...) {
        position_known = false;
        throw;
      }
      convert_current(base + slot * frame_bytes);
    }
    return out;
  }

  std::vector<int64_t> range_indices(int64_t start, int64_t count, int64_t stride) const {
    if (stride < 1) throw Error("frame stride must be >= 1, got " + std::to_string(stride));
    check_index(start);
    const int64_t available = (info.frames - start + stride - 1) / stride;
    if (count < 0) count = available;
    if (count > available)
      throw Error("frame index " + std::to_string(start + (count - 1) * stride) + " out of range for '" +
                  path + "' (" + std::to_string(info.frames) + " frames)");
    std::vector<int64_t> indices(count);
    for (int64_t i = 0; i < count; ++i) indices[i] = start + i * stride;
    return indices;
  }
};

VideoReader::VideoReader(const std::string& path, VideoReaderOptions options)
    : impl_(std::make_unique<Impl>(path, options)) {}
VideoReader::~VideoReader() = default;
VideoReader::VideoReader(VideoReader&&) noexcept = default;
VideoReader& VideoReader::operator=(VideoReader&&) noexcept = default;

const VideoInfo& VideoReader::info() const { return impl_->info; }
int64_t VideoReader::num_frames() const { return impl_->info.frames; }
const std::string& VideoReader::path() const { return impl_->path; }

at::Tensor VideoReader::read_frame(int64_t index) { return impl_->read_sorted({index}).squeeze(0); }

at::Tensor VideoReader::read_frames(const std::vector<int64_t>& indices) {
  return impl_->read_sorted(indices);
}

at::Tensor VideoReader::read_range(int64_t start, int64_t count, int64_t stride) {
  return impl_->read_sorted(impl_->range_indices(start, count, stride));
}

at::Tensor VideoReader::read_all() { return read_range(0, -1, 1); }

void VideoReader::for_each_frame(int64_t start, int64_t count, int64_t stride,
                                 const std::function<void(int64_t, const at::Tensor&)>& fn) {
  const auto indices = impl_->range_indices(start, count, stride);
  auto buffer = torch::empty({impl_->info.height, impl_->info.width, 3}, torch::kUInt8);  // [H, W, 3]
  for (int64_t index : indices) {
    try {
      impl_->decode_to(index);
    } catch (...) {
      impl_->position_known = false;
      throw;
    }
    impl_->convert_current(buffer.data_ptr<uint8_t>());
    fn(index, buffer);
  }
}

VideoInfo probe_video(const std::string& path) { return VideoReader(path).info(); }

double measure_decode_fps(const std::string& path, int repeats, VideoReaderOptions options,
                          int64_t max_frames) {
  std::vector<double> rates;
  for (int r = 0; r < std::max(1, repeats); ++r) {
    VideoReader reader(path, options);
    const int64_t count = max_frames < 0 ? reader.num_frames() : std::min(max_frames, reader.num_frames());
    int64_t decoded = 0;
    const auto start = std::chrono::steady_clock::now();
    reader.for_each_frame(0, count, 1, [&](int64_t, const at::Tensor&) { ++decoded; });
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    rates.push_back(static_cast<double>(decoded) / std::max(seconds, 1e-9));
  }
  std::sort(rates.begin(), rates.end());
  return rates[rates.size() / 2];
}

}  // namespace dojo::io
