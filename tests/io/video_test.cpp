// Video I/O: probing and frame-accurate decoding of real camera clips (Debian's opencv-doc)
// and of clips in other codecs made with the ffmpeg CLI; transforms; H.264/PNG encoding;
// comparison videos; error messages; the `dojo video` command.
#include "io/video.h"

#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <functional>
#include <map>
#include <nlohmann/json.hpp>

#include "core/error.h"
#include "test_util.h"

namespace dojo {
namespace {

namespace fs = std::filesystem;

// Facts about the opencv-doc clips, taken once from
// `ffprobe -count_frames -show_entries stream=codec_name,width,height,r_frame_rate,nb_read_frames`.
struct ClipFacts {
  const char* name;
  int64_t frames;
  int width, height;
  double fps;
  const char* codec;
};
constexpr ClipFacts kVtest{"vtest.avi", 795, 768, 576, 10.0, "msmpeg4v3"};
constexpr ClipFacts kMegamind{"Megamind.avi", 270, 720, 528, 2997.0 / 125.0, "mpeg4"};
// The AVI header of tree.avi claims 444 frames; 376 of them are dropped-frame placeholders.
constexpr ClipFacts kTree{"tree.avi", 68, 320, 240, 1000000.0 / 66667.0, "cinepak"};

#define REQUIRE_SAMPLE(var, name)                \
  const fs::path var = test::sample_video(name); \
  if (var.empty()) GTEST_SKIP() << name << " not installed (apt install opencv-doc)"

bool has_ffmpeg_cli() { return std::system("ffmpeg -version > /dev/null 2>&1") == 0; }

bool has_encoder(const std::string& name) {
  static const std::string encoders = test::run_command("ffmpeg -hide_banner -encoders").output;
  return encoders.find(" " + name + " ") != std::string::npos;
}

void run_or_fail(const std::string& command) {
  // timeout: a wrong option must not hang the suite.
  ASSERT_EQ(std::system(("timeout 120 " + command + " > /dev/null 2>&1").c_str()), 0) << command;
}

// Moving smooth colour waves and a bouncing brighter square, different on every frame. Colour
// varies smoothly and the square changes brightness only, because yuv420p stores colour at half
// resolution: sharp colour edges would measure chroma subsampling, not the codec path.
torch::Tensor synthetic_clip(int64_t t, int64_t h, int64_t w) {
  auto y = torch::arange(h, torch::kFloat32).view({1, h, 1});
  auto x = torch::arange(w, torch::kFloat32).view({1, 1, w});
  auto k = torch::arange(t, torch::kFloat32).view({t, 1, 1});
  auto square = torch::zeros({t, h, w});
  const int64_t side = std::max<int64_t>(4, h / 4);
  for (int64_t i = 0; i < t; ++i) {
    const int64_t top = (i * 3) % (h - side), left = (i * 5) % (w - side);
    square[i].slice(0, top, top + side).slice(1, left, left + side).fill_(50);
  }
  auto r = 118 + 80 * torch::sin(x / 11.0 + k * 0.25) + square;
  auto g = 118 + 80 * torch::cos(y / 9.0 - k * 0.2) + square;
  auto b = 118 + 60 * torch::sin((x + y) / 15.0 + k * 0.1) + square;
  return torch::stack({r, g, b}, 3).round().clamp(0, 255).to(torch::kUInt8).contiguous();  // [T, H, W, 3]
}

double psnr(const torch::Tensor& a, const torch::Tensor& b) {
  const double mse = (a.to(torch::kFloat64) - b.to(torch::kFloat64)).pow(2).mean().item<double>();
  return mse == 0 ? 99.0 : 10.0 * std::log10(255.0 * 255.0 / mse);
}

double mean_abs_diff(const torch::Tensor& a, const torch::Tensor& b) {
  return (a.to(torch::kFloat32) - b.to(torch::kFloat32)).abs().mean().item<double>();
}

std::string read_bytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

// Reads frames [0, count) strictly sequentially (forward chunks never seek) and returns the
// ones in `keep`, as the reference for random access.
std::map<int64_t, torch::Tensor> sequential_frames(const fs::path& path, int64_t count,
                                                   const std::vector<int64_t>& keep) {
  io::VideoReader reader(path.string());
  std::map<int64_t, torch::Tensor> out;
  reader.for_each_frame(0, count, 1, [&](int64_t index, const at::Tensor& frame) {
    if (std::find(keep.begin(), keep.end(), index) != keep.end()) out[index] = frame.clone();
  });
  return out;
}

// Random reads (one reader, arbitrary order, forcing backward and forward seeks) must equal
// the sequential decode.
void expect_random_access_matches(const fs::path& path, const std::vector<int64_t>& indices) {
  const int64_t last = *std::max_element(indices.begin(), indices.end());
  const auto reference = sequential_frames(path, last + 1, indices);
  io::VideoReader reader(path.string());
  const auto batch = reader.read_frames(indices);  // [T, H, W, 3]
  for (size_t i = 0; i < indices.size(); ++i)
    EXPECT_TRUE(torch::equal(batch[i], reference.at(indices[i])))
        << path << " frame " << indices[i] << " (batch)";
  for (auto it = indices.rbegin(); it != indices.rend(); ++it)
    EXPECT_TRUE(torch::equal(reader.read_frame(*it), reference.at(*it)))
        << path << " frame " << *it << " (single)";
}

// Frame `index` decoded by the ffmpeg CLI (its select filter counts output frames like we do;
// with the same scaler flags the pixels are identical to ours).
torch::Tensor ffmpeg_frame(const fs::path& path, int64_t index, int width, int height, const fs::path& tmp) {
  const fs::path raw = tmp / ("frame_" + std::to_string(index) + ".rgb");
  const std::string command = "ffmpeg -nostdin -v error -y -i '" + path.string() +
                              "' -sws_flags bilinear+accurate_rnd+full_chroma_int -vf 'select=eq(n\\," +
                              std::to_string(index) + ")' -frames:v 1 -f rawvideo -pix_fmt rgb24 '" +
                              raw.string() + "'";
  EXPECT_EQ(std::system(command.c_str()), 0) << command;
  const std::string bytes = read_bytes(raw);
  EXPECT_EQ(static_cast<int64_t>(bytes.size()), int64_t{width} * height * 3);
  auto frame = torch::zeros({height, width, 3}, torch::kUInt8);
  std::memcpy(frame.data_ptr<uint8_t>(), bytes.data(), std::min<size_t>(bytes.size(), frame.numel()));
  return frame;
}

void expect_error_mentions(const std::function<void()>& fn, const std::vector<std::string>& needles) {
  try {
    fn();
    ADD_FAILURE() << "expected dojo::Error";
  } catch (const Error& e) {
    for (const auto& needle : needles)
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what() << " lacks " << needle;
  }
}

// --- probing real clips ------------------------------------------------------------------------

void expect_facts(const ClipFacts& facts) {
  const fs::path path = test::sample_video(facts.name);
  if (path.empty()) GTEST_SKIP() << facts.name << " not installed";
  const io::VideoInfo info = io::probe_video(path.string());
  EXPECT_EQ(info.frames, facts.frames) << facts.name;
  EXPECT_EQ(info.width, facts.width) << facts.name;
  EXPECT_EQ(info.height, facts.height) << facts.name;
  EXPECT_NEAR(info.fps, facts.fps, 1e-3) << facts.name;
  EXPECT_EQ(info.codec, facts.codec) << facts.name;
  EXPECT_EQ(info.container, "avi");
  EXPECT_GT(info.keyframes, 0);
}

TEST(VideoInfo, VtestMatchesFfprobe) {
  expect_facts(kVtest);
  REQUIRE_SAMPLE(path, "vtest.avi");
  const auto info = io::probe_video(path.string());
  EXPECT_NEAR(info.duration_s, 79.5, 1e-6);
  EXPECT_EQ(info.pixel_format, "yuv420p");
  const auto json = info.to_json();
  EXPECT_EQ(json["frames"], 795);
  EXPECT_EQ(json["codec"], "msmpeg4v3");
}
TEST(VideoInfo, MegamindMatchesFfprobe) { expect_facts(kMegamind); }
TEST(VideoInfo, TreeCountsRealPicturesNotAviPlaceholders) { expect_facts(kTree); }

// --- frame-accurate decoding of real clips -----------------------------------------------------

TEST(VideoReader, VtestRandomAccessEqualsSequential) {
  REQUIRE_SAMPLE(path, "vtest.avi");
  io::VideoReader reader(path.string());
  ASSERT_EQ(reader.num_frames(), 795);
  // Frames around the keyframes (0 and the ones inside) and the last one.
  expect_random_access_matches(path, {794, 0, 1, 233, 232, 400, 401, 599, 3, 794});
}

TEST(VideoReader, MegamindBFramesWithoutTimestampsEqualSequential) {
  // MPEG-4 ASP with packed B-frames in AVI: most packets carry no pts (counting mode).
  REQUIRE_SAMPLE(path, "Megamind.avi");
  expect_random_access_matches(path, {269, 0, 97, 98, 99, 100, 153, 154, 155, 200, 201, 202, 50, 2});
}

TEST(VideoReader, MegamindBugyEqualsSequential) {
  REQUIRE_SAMPLE(path, "Megamind_bugy.avi");
  expect_random_access_matches(path, {269, 39, 40, 41, 42, 75, 76, 99, 100, 101, 102, 0});
}

TEST(VideoReader, TreeEqualsSequential) {
  REQUIRE_SAMPLE(path, "tree.avi");
  expect_random_access_matches(path, {67, 0, 30, 31, 66, 1});
}

TEST(VideoReader, FrameNumbersAgreeWithFfmpegCli) {
  // Guards against off-by-one indexing (seeking and the sequential path could agree and both be
  // wrong): our frame k is ffmpeg's frame k, pixel for pixel, and not its neighbour.
  if (!has_ffmpeg_cli()) GTEST_SKIP() << "ffmpeg CLI not installed";
  test::TempDir tmp;
  int checked = 0;
  for (const auto& [facts, frames] : {std::pair{kMegamind, std::vector<int64_t>{3, 154, 201}},
                                      std::pair{kVtest, std::vector<int64_t>{500}}}) {
    const fs::path path = test::sample_video(facts.name);
    if (path.empty()) continue;
    io::VideoReader reader(path.string());
    for (int64_t k : frames) {
      const auto theirs = ffmpeg_frame(path, k, facts.width, facts.height, tmp.path());
      EXPECT_TRUE(torch::equal(reader.read_frame(k), theirs)) << facts.name << " frame " << k;
      EXPECT_FALSE(torch::equal(reader.read_frame(k - 1), theirs)) << facts.name << " frame " << k;
      EXPECT_FALSE(torch::equal(reader.read_frame(k + 1), theirs)) << facts.name << " frame " << k;
      ++checked;
    }
  }
  if (checked == 0) GTEST_SKIP() << "opencv-doc clips not installed";
}

TEST(VideoReader, RangeStrideAndDuplicates) {
  REQUIRE_SAMPLE(path, "Megamind.avi");
  io::VideoReader reader(path.string());
  const auto strided = reader.read_range(10, 5, 7);  // frames 10, 17, 24, 31, 38
  ASSERT_EQ(strided.sizes(), (std::vector<int64_t>{5, 528, 720, 3}));
  const auto picked = reader.read_frames({38, 10, 24, 17, 31, 10});
  EXPECT_TRUE(torch::equal(strided[0], picked[1]));
  EXPECT_TRUE(torch::equal(strided[1], picked[3]));
  EXPECT_TRUE(torch::equal(strided[2], picked[2]));
  EXPECT_TRUE(torch::equal(strided[3], picked[4]));
  EXPECT_TRUE(torch::equal(strided[4], picked[0]));
  EXPECT_TRUE(torch::equal(picked[1], picked[5]));
  EXPECT_FALSE(torch::equal(strided[0], strided[1]));
  // count < 0: every stride-th frame through the end: 260, 263, 266, 269.
  EXPECT_EQ(reader.read_range(260, -1, 3).size(0), 4);
  std::vector<int64_t> seen;
  reader.for_each_frame(265, -1, 2, [&](int64_t i, const at::Tensor& f) {
    seen.push_back(i);
    EXPECT_EQ(f.sizes(), (std::vector<int64_t>{528, 720, 3}));
  });
  EXPECT_EQ(seen, (std::vector<int64_t>{265, 267, 269}));
}

TEST(VideoReader, IndexOutOfRangeNamesFileAndIndex) {
  REQUIRE_SAMPLE(path, "tree.avi");
  io::VideoReader reader(path.string());
  expect_error_mentions([&] { reader.read_frame(68); }, {"68", "tree.avi"});
  expect_error_mentions([&] { reader.read_frame(-1); }, {"-1", "tree.avi"});
  expect_error_mentions([&] { reader.read_range(60, 5, 2); }, {"68", "tree.avi"});
  expect_error_mentions([&] { reader.read_range(0, 2, 0); }, {"stride"});
  // The reader stays usable after errors.
  EXPECT_EQ(reader.read_frame(67).size(0), 240);
}

// --- errors ------------------------------------------------------------------------------------

TEST(VideoReader, MissingGarbageAndTextFilesNameTheFile) {
  test::TempDir tmp;
  const std::string missing = (tmp / "missing_clip.mp4").string();
  expect_error_mentions([&] { io::VideoReader r(missing); }, {missing, "not found"});
  const std::string garbage = (tmp / "garbage_clip.mp4").string();
  {
    std::ofstream out(garbage, std::ios::binary);
    uint32_t state = 12345;
    for (int i = 0; i < 20000; ++i) {
      state = state * 1664525u + 1013904223u;
      out.put(static_cast<char>(state >> 24));
    }
  }
  expect_error_mentions([&] { io::VideoReader r(garbage); }, {garbage});
  const std::string text = (tmp / "notes.txt").string();
  std::ofstream(text) << "not a video\n";
  expect_error_mentions([&] { io::VideoReader r(text); }, {text});
  expect_error_mentions([&] { io::VideoReader r(tmp.path().string()); }, {tmp.path().string()});
}

TEST(VideoReader, TruncatedAviDecodesWhatIsThere) {
  REQUIRE_SAMPLE(path, "Megamind.avi");
  test::TempDir tmp;
  const fs::path cut = tmp / "megamind_cut.avi";
  const std::string bytes = read_bytes(path);
  std::ofstream(cut, std::ios::binary)
      .write(bytes.data(), static_cast<std::streamsize>(bytes.size() * 3 / 10));
  io::VideoReader reader(cut.string());
  const int64_t n = reader.num_frames();
  EXPECT_GT(n, 10);
  EXPECT_LT(n, 270);
  // What is there decodes like the intact file.
  io::VideoReader full(path.string());
  EXPECT_TRUE(torch::equal(reader.read_frame(n / 2), full.read_frame(n / 2)));
  EXPECT_EQ(reader.read_frame(n - 1).size(1), 720);
  expect_error_mentions([&] { reader.read_frame(n); }, {cut.string(), std::to_string(n)});
}

TEST(VideoReader, TruncatedMp4NamesTheFile) {
  test::TempDir tmp;
  const fs::path good = tmp / "good.mp4";
  io::write_video(good.string(), synthetic_clip(30, 64, 96), {});
  const std::string bytes = read_bytes(good);
  // faststart puts the index first: the cut file opens, the frames that are there decode, and
  // frames past the cut are out of range.
  const fs::path cut = tmp / "cut_faststart.mp4";
  std::ofstream(cut, std::ios::binary)
      .write(bytes.data(), static_cast<std::streamsize>(bytes.size() * 3 / 10));
  io::VideoReader reader(cut.string());
  EXPECT_GT(reader.num_frames(), 0);
  EXPECT_LT(reader.num_frames(), 30);
  EXPECT_EQ(reader.read_all().size(0), reader.num_frames());
  expect_error_mentions([&] { reader.read_frame(29); }, {cut.string(), "29"});
  // Without faststart the index is at the end and the cut file cannot be opened.
  const fs::path slow = tmp / "slow.mp4";
  io::VideoWriterOptions options;
  options.faststart = false;
  io::write_video(slow.string(), synthetic_clip(30, 64, 96), options);
  const std::string slow_bytes = read_bytes(slow);
  const fs::path slow_cut = tmp / "cut_slow.mp4";
  std::ofstream(slow_cut, std::ios::binary)
      .write(slow_bytes.data(), static_cast<std::streamsize>(slow_bytes.size() * 3 / 10));
  expect_error_mentions([&] { io::VideoReader r(slow_cut.string()); }, {slow_cut.string()});
}

// --- other codecs, made with the ffmpeg CLI ----------------------------------------------------

struct CodecCase {
  const char* encoder;
  const char* file;
  const char* args;
  const char* codec;
};

TEST(VideoReader, GeneratedCodecsDecodeWithCorrectCount) {
  if (!has_ffmpeg_cli()) GTEST_SKIP() << "ffmpeg CLI not installed";
  const CodecCase cases[] = {
      // Audio as stream 0: the reader must pick the video stream and skip audio packets.
      {"libx264", "h264_audio.mkv",
       "-map 1:a -map 0:v -c:a flac -t 1.2 -c:v libx264 -preset ultrafast -bf 2 -g 5", "h264"},
      {"libx265", "hevc.mp4", "-map 0:v -c:v libx265 -preset ultrafast -x265-params log-level=none:keyint=5",
       "hevc"},
      {"libvpx-vp9", "vp9.webm", "-map 0:v -c:v libvpx-vp9 -deadline realtime -cpu-used 8 -g 5", "vp9"},
      {"libaom-av1", "av1.mkv", "-map 0:v -c:v libaom-av1 -cpu-used 8 -crf 50 -g 5", "av1"},
      {"libsvtav1", "av1_svt.mkv", "-map 0:v -c:v libsvtav1 -preset 12 -g 5", "av1"},
      {"mpeg4", "mpeg4.avi", "-map 0:v -c:v mpeg4 -bf 2 -g 5 -q:v 5", "mpeg4"},
  };
  test::TempDir tmp;
  bool av1_done = false;
  int tested = 0;
  for (const auto& c : cases) {
    if (!has_encoder(c.encoder) || (std::string(c.codec) == "av1" && av1_done)) continue;
    SCOPED_TRACE(c.file);
    const fs::path path = tmp / c.file;
    run_or_fail(
        "ffmpeg -nostdin -v error -y -f lavfi -i testsrc2=size=96x64:rate=10 -f lavfi -i "
        "sine=sample_rate=8000:duration=1.2 "
        "-frames:v 12 -pix_fmt yuv420p " +
        std::string(c.args) + " '" + path.string() + "'");
    io::VideoReader reader(path.string());
    EXPECT_EQ(reader.num_frames(), 12);
    EXPECT_EQ(reader.info().codec, c.codec);
    EXPECT_EQ(reader.info().width, 96);
    EXPECT_EQ(reader.info().height, 64);
    EXPECT_NEAR(reader.info().fps, 10.0, 1e-6);
    EXPECT_EQ(reader.read_all().size(0), 12);
    expect_random_access_matches(path, {11, 0, 6, 5, 7, 3});
    if (std::string(c.codec) == "av1") av1_done = true;
    ++tested;
  }
  if (tested == 0) GTEST_SKIP() << "no test encoders in this ffmpeg";
}

TEST(VideoReader, EditListCutSkipsDiscardedFrames) {
  // Stream-copying from 0.45 s makes an mp4 whose edit list starts mid-GOP: the 5 packets
  // before the cut are decoded as references but are not frames.
  if (!has_ffmpeg_cli() || !has_encoder("libx264")) GTEST_SKIP() << "ffmpeg CLI with libx264 not installed";
  test::TempDir tmp;
  const fs::path source = tmp / "source.mp4", cut = tmp / "cut.mp4";
  run_or_fail(
      "ffmpeg -nostdin -v error -y -f lavfi -i testsrc2=size=96x64:rate=10 -frames:v 30 -pix_fmt yuv420p "
      "-c:v libx264 -g 10 -bf 2 '" +
      source.string() + "'");
  run_or_fail("ffmpeg -nostdin -v error -y -ss 0.45 -i '" + source.string() + "' -c copy '" + cut.string() +
              "'");
  io::VideoReader reader(cut.string());
  ASSERT_EQ(reader.num_frames(), 25);
  io::VideoReader original(source.string());
  EXPECT_TRUE(torch::equal(reader.read_frame(0), original.read_frame(5)));
  EXPECT_TRUE(torch::equal(reader.read_frame(24), original.read_frame(29)));
  expect_random_access_matches(cut, {24, 0, 1, 12, 5, 6});
}

// --- transforms --------------------------------------------------------------------------------

TEST(VideoTransforms, CropBoxRule) {
  // Megamind 720x528 at 4:3 -> 704x528, left (720-704)/2 = 8.
  auto box = io::center_crop_box(528, 720, 4, 3);
  EXPECT_EQ(box.height, 528);
  EXPECT_EQ(box.width, 704);
  EXPECT_EQ(box.left, 8);
  EXPECT_EQ(box.top, 0);
  // 5 x 8 to square: 5x5, left floor(3/2) = 1.
  box = io::center_crop_box(5, 8, 1, 1);
  EXPECT_EQ(box.width, 5);
  EXPECT_EQ(box.left, 1);
  // Too tall: 100 x 30 at 16:9 -> height round(30 * 9 / 16 = 16.875) = 17, top floor(83/2) = 41.
  box = io::center_crop_box(100, 30, 16, 9);
  EXPECT_EQ(box.height, 17);
  EXPECT_EQ(box.width, 30);
  EXPECT_EQ(box.top, 41);
}

TEST(VideoTransforms, CenterCropPicksTheHandComputedPixels) {
  // A 1 x 5 x 6 image whose red channel is row * 10 + column.
  auto image = torch::zeros({1, 5, 6, 3}, torch::kUInt8);
  for (int r = 0; r < 5; ++r)
    for (int c = 0; c < 6; ++c) image[0][r][c][0] = r * 10 + c;
  // 2 x 3 crop: top floor((5-2)/2) = 1, left floor((6-3)/2) = 1.
  const auto crop = io::center_crop(image, 2, 3);
  ASSERT_EQ(crop.sizes(), (std::vector<int64_t>{1, 2, 3, 3}));
  EXPECT_EQ(crop[0][0][0][0].item<int>(), 11);
  EXPECT_EQ(crop[0][1][2][0].item<int>(), 23);
  // Square crop of 5 x 6: 5 x 5 at left 0 (floor(1/2)).
  const auto square = io::center_crop_aspect(image[0], 1, 1);
  ASSERT_EQ(square.sizes(), (std::vector<int64_t>{5, 5, 3}));
  EXPECT_EQ(square[4][4][0].item<int>(), 44);
  EXPECT_EQ(io::center_crop_4x3(torch::zeros({480, 720, 3}, torch::kUInt8)).sizes(),
            (std::vector<int64_t>{480, 640, 3}));
}

TEST(VideoTransforms, ResizeCenterCrop) {
  const auto clip = synthetic_clip(3, 48, 80);
  const auto out = io::resize_center_crop(clip, 16, 16);
  ASSERT_EQ(out.sizes(), (std::vector<int64_t>{3, 16, 16, 3}));
  EXPECT_EQ(out.scalar_type(), torch::kUInt8);
  // Uniform colour survives cropping and (antialiased) resizing exactly.
  const auto flat = torch::full({2, 37, 53, 3}, 77, torch::kUInt8);
  EXPECT_TRUE(
      torch::equal(io::resize_center_crop(flat, 24, 32), torch::full({2, 24, 32, 3}, 77, torch::kUInt8)));
  // Same size is the identity; a single frame keeps its rank.
  EXPECT_TRUE(torch::equal(io::resize(clip, 48, 80), clip));
  EXPECT_EQ(io::resize_center_crop(clip[0], 30, 40).sizes(), (std::vector<int64_t>{30, 40, 3}));
  // Cropping first: the centre of the crop is the centre of the frame.
  auto marked = torch::zeros({1, 40, 80, 3}, torch::kUInt8);
  marked.slice(2, 20, 60).fill_(200);  // the central 40 x 40 square
  EXPECT_TRUE(
      torch::equal(io::resize_center_crop(marked, 10, 10), torch::full({1, 10, 10, 3}, 200, torch::kUInt8)));
}

// --- encoding ----------------------------------------------------------------------------------

TEST(VideoWriter, RoundTripQualityCountAndFps) {
  test::TempDir tmp;
  const fs::path path = tmp / "roundtrip.mp4";
  const auto clip = synthetic_clip(24, 96, 128);  // [T, H, W, 3]
  io::VideoWriterOptions options;
  options.fps = 15;
  {
    io::VideoWriter writer(path.string(), options);
    writer.write_many(clip.slice(0, 0, 20));
    for (int t = 20; t < 24; ++t) writer.write(clip[t]);
    EXPECT_EQ(writer.frames_written(), 24);
    EXPECT_FALSE(fs::exists(path)) << "the video must appear only when closed";
    writer.close();
  }
  io::VideoReader reader(path.string());
  EXPECT_EQ(reader.num_frames(), 24);
  EXPECT_NEAR(reader.info().fps, 15.0, 1e-9);
  EXPECT_EQ(reader.info().codec, "h264");
  EXPECT_EQ(reader.info().pixel_format, "yuv420p");
  const auto decoded = reader.read_all();
  ASSERT_EQ(decoded.sizes(), clip.sizes());
  EXPECT_GT(psnr(decoded, clip), 38.0);
  // Frame order survives B-frames: each decoded frame is closest to its own source frame.
  for (int t : {0, 5, 23})
    EXPECT_LT(mean_abs_diff(decoded[t], clip[t]), mean_abs_diff(decoded[t], clip[t ^ 1]));
  // Random access over B-frames and 1-second GOPs.
  expect_random_access_matches(path, {23, 0, 14, 15, 16, 7});
}

TEST(VideoWriter, RepeatedEncodesAreByteIdentical) {
  // Widths of 96 and 320 px made x264's macroblock-tree read uninitialised memory, so the 2nd or
  // 3rd encode in a process differed; the writer turns it off.
  test::TempDir tmp;
  for (const auto& [h, w] : {std::pair{64, 96}, std::pair{48, 320}}) {
    const auto clip = synthetic_clip(20, h, w);
    std::vector<std::string> files;
    for (int i = 0; i < 3; ++i) {
      const fs::path path = tmp / ("enc" + std::to_string(i) + ".mp4");
      io::write_video(path.string(), i == 1 ? clip.clone() : clip);
      files.push_back(read_bytes(path));
    }
    EXPECT_GT(files[0].size(), 1000u);
    EXPECT_TRUE(files[0] == files[1]) << h << "x" << w;
    EXPECT_TRUE(files[0] == files[2]) << h << "x" << w;
    // faststart: the index ('moov') precedes the media data ('mdat').
    EXPECT_LT(files[0].find("moov"), files[0].find("mdat"));
  }
}

TEST(VideoWriter, OddSizeIsPaddedAndFractionalFpsKept) {
  test::TempDir tmp;
  const fs::path path = tmp / "odd.mp4";
  io::VideoWriterOptions options;
  options.fps = 30000.0 / 1001.0;
  io::write_video(path.string(), synthetic_clip(6, 33, 47), options);
  io::VideoReader reader(path.string());
  EXPECT_EQ(reader.info().height, 34);
  EXPECT_EQ(reader.info().width, 48);
  EXPECT_NEAR(reader.info().fps, 30000.0 / 1001.0, 1e-6);
  EXPECT_EQ(reader.num_frames(), 6);
}

TEST(VideoWriter, BadInputAndEmptyWriterErrors) {
  test::TempDir tmp;
  const std::string path = (tmp / "bad.mp4").string();
  {
    io::VideoWriter writer(path);
    expect_error_mentions([&] { writer.write(torch::zeros({8, 8, 3}, torch::kFloat32)); }, {"uint8"});
    expect_error_mentions([&] { writer.write(torch::zeros({8, 8}, torch::kUInt8)); }, {"[H, W, 3]"});
    writer.write(torch::zeros({8, 8, 3}, torch::kUInt8));
    expect_error_mentions([&] { writer.write(torch::zeros({10, 8, 3}, torch::kUInt8)); }, {path, "10x8"});
    writer.close();
  }
  EXPECT_EQ(io::probe_video(path).frames, 1);
  const std::string empty = (tmp / "empty.mp4").string();
  io::VideoWriter writer(empty);
  expect_error_mentions([&] { writer.close(); }, {empty, "no frames"});
  EXPECT_FALSE(fs::exists(empty));
  expect_error_mentions(
      [&] { io::write_video((tmp / "no/such/dir/x.mp4").string(), synthetic_clip(2, 8, 8)); },
      {"no/such/dir"});
}

TEST(VideoWriter, UnwindingWriterLeavesNoFile) {
  test::TempDir tmp;
  const fs::path path = tmp / "partial.mp4";
  try {
    io::VideoWriter writer(path.string());
    writer.write(synthetic_clip(1, 16, 16)[0]);
    throw std::runtime_error("simulated failure");
  } catch (const std::runtime_error&) {
  }
  EXPECT_TRUE(fs::is_empty(tmp.path())) << "neither the video nor its temporary file may remain";
}

TEST(VideoPng, WriteAndReadBackLossless) {
  test::TempDir tmp;
  const auto clip = synthetic_clip(3, 20, 30);
  const auto paths = io::write_png_frames((tmp / "pngs").string(), clip, "frame_", 7);
  ASSERT_EQ(paths.size(), 3u);
  EXPECT_EQ(fs::path(paths[0]).filename(), "frame_000007.png");
  for (int t = 0; t < 3; ++t) {
    io::VideoReader png(paths[t]);
    EXPECT_EQ(png.info().codec, "png");
    EXPECT_EQ(png.num_frames(), 1);
    EXPECT_TRUE(torch::equal(png.read_frame(0), clip[t]));
  }
}

// --- text and comparison videos ----------------------------------------------------------------

TEST(VideoOverlay, DrawTextGlyphPixels) {
  auto image = torch::zeros({9, 14, 3}, torch::kUInt8);
  io::draw_text(image, "A1", 1, 1, 1, {255, 0, 0});
  auto red = image.select(2, 0);  // [H, W]
  // 'A' top row is .###. starting at x = 1.
  EXPECT_EQ(red[1][1].item<int>(), 0);
  EXPECT_EQ(red[1][2].item<int>(), 255);
  EXPECT_EQ(red[1][4].item<int>(), 255);
  EXPECT_EQ(red[1][5].item<int>(), 0);
  // 'A' row 3 is ##### (crossbar).
  EXPECT_EQ(red.slice(1, 1, 6)[4].sum().item<int>(), 5 * 255);
  // '1' starts one cell (6 px) later; its bottom row is .###.
  EXPECT_EQ(red[7].slice(0, 7, 12).sum().item<int>(), 3 * 255);
  EXPECT_EQ(image.select(2, 1).sum().item<int>(), 0);
  EXPECT_EQ(io::text_size("A1", 2), (std::array<int64_t, 2>{22, 14}));
  // Clipping at the borders is not an error.
  io::draw_text(image, "WWWWWW", -3, 5, 2);
}

TEST(VideoOverlay, ComparisonVideoLayout) {
  const auto truth = synthetic_clip(6, 40, 50);
  const auto pred = synthetic_clip(4, 30, 31);
  const auto canvas = io::compose_side_by_side({truth, pred}, {"ground truth", "prediction"});
  // Label strip 8 + 2 + 2 = 12 px; height 12 + 40 = 52; width 50 + 4 + 31 = 85 -> 86 (even).
  ASSERT_EQ(canvas.sizes(), (std::vector<int64_t>{6, 52, 86, 3}));
  EXPECT_TRUE(torch::equal(canvas.slice(1, 12, 52).slice(2, 0, 50), truth));
  EXPECT_TRUE(torch::equal(canvas.slice(1, 12, 42).slice(2, 54, 85).slice(0, 0, 4), pred));
  // The shorter prediction holds its last frame.
  EXPECT_TRUE(torch::equal(canvas[5].slice(0, 12, 42).slice(1, 54, 85), pred[3]));
  // Labels are drawn in the strips.
  EXPECT_GT(canvas[0].slice(0, 0, 12).slice(1, 0, 50).sum().item<int64_t>(), 0);
  EXPECT_GT(canvas[0].slice(0, 0, 12).slice(1, 54, 85).sum().item<int64_t>(), 0);
  // Below the shorter panel is black.
  EXPECT_EQ(canvas.slice(1, 42, 52).slice(2, 54, 85).sum().item<int64_t>(), 0);

  test::TempDir tmp;
  const fs::path path = tmp / "compare.mp4";
  io::write_comparison_video(path.string(), {truth, pred}, {"ground truth", "prediction"}, 5.0);
  io::VideoReader reader(path.string());
  EXPECT_EQ(reader.info().width, 86);
  EXPECT_EQ(reader.info().height, 52);
  EXPECT_EQ(reader.num_frames(), 6);
  EXPECT_NEAR(reader.info().fps, 5.0, 1e-9);
  expect_error_mentions([&] { io::compose_side_by_side({truth}, {"a", "b"}); }, {"2 labels for 1 videos"});
}

// --- decode speed helper -----------------------------------------------------------------------

TEST(VideoBench, MeasureDecodeFpsIsPositive) {
  test::TempDir tmp;
  const fs::path path = tmp / "bench.mp4";
  io::write_video(path.string(), synthetic_clip(10, 32, 32));
  io::VideoReaderOptions options;
  options.threads = 1;
  const double fps = io::measure_decode_fps(path.string(), 2, options);
  EXPECT_TRUE(std::isfinite(fps));
  EXPECT_GT(fps, 0.0);
}

// --- the `dojo video` command ------------------------------------------------------------------

TEST(VideoCli, InfoJson) {
  REQUIRE_SAMPLE(path, "vtest.avi");
  const auto result = test::run_dojo("video info '" + path.string() + "' --json");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto json = nlohmann::json::parse(result.output);
  EXPECT_EQ(json["frames"], 795);
  EXPECT_EQ(json["width"], 768);
  EXPECT_EQ(json["height"], 576);
  EXPECT_EQ(json["fps"], 10.0);
  EXPECT_EQ(json["codec"], "msmpeg4v3");
}

TEST(VideoCli, FramesWritesPngs) {
  test::TempDir tmp;
  const fs::path clip = tmp / "clip.mp4";
  io::write_video(clip.string(), synthetic_clip(12, 48, 64));
  const fs::path out = tmp / "out";
  const auto result = test::run_dojo("video frames '" + clip.string() + "' --out '" + out.string() +
                                     "' --start 2 --count 3 --stride 4 --size 32x32 --json");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  for (const char* name : {"frame_000002.png", "frame_000006.png", "frame_000010.png"}) {
    ASSERT_TRUE(fs::exists(out / name)) << name << "\n" << result.output;
    const auto info = io::probe_video((out / name).string());
    EXPECT_EQ(info.width, 32);
    EXPECT_EQ(info.height, 32);
  }
  EXPECT_EQ(std::distance(fs::directory_iterator(out), fs::directory_iterator{}), 3);
}

TEST(VideoCli, ErrorsExitNonZeroNamingTheFile) {
  test::TempDir tmp;
  const std::string missing = (tmp / "nope.mp4").string();
  auto result = test::run_dojo("video info '" + missing + "'");
  EXPECT_EQ(result.exit_code, 1);
  EXPECT_NE(result.output.find(missing), std::string::npos) << result.output;
  result = test::run_dojo("video frames '" + missing + "' --out '" + tmp.path().string() + "' --size 12");
  EXPECT_EQ(result.exit_code, 2) << result.output;
  EXPECT_NE(result.output.find("HxW"), std::string::npos) << result.output;
  result = test::run_dojo("video --help");
  EXPECT_EQ(result.exit_code, 0);
  EXPECT_NE(result.output.find("frames"), std::string::npos);
}

}  // namespace
}  // namespace dojo
