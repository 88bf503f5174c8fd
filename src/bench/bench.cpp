#include "bench/bench.h"

#include <torch/torch.h>

#include <unistd.h>
#include <chrono>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <sstream>

#include "core/error.h"

#include "core/log.h"
#include "core/runtime.h"
#include "core/timing.h"
#include "data/clip_loader.h"
#include "io/parquet.h"
#include "io/parquet_writer.h"
#include "io/video.h"
#ifdef DOJO_WITH_SIM
#include "sim/episode.h"
#include "sim/generate.h"
#include "sim/renderer.h"
#include "sim/scene.h"
#endif

namespace dojo::bench {
namespace {

std::vector<std::function<std::vector<BenchCase>(const BenchOptions&)>>& factories() {
  static std::vector<std::function<std::vector<BenchCase>(const BenchOptions&)>> list;
  return list;
}

// Square matmul: the practical roofline for everything built from GEMMs, in float32 and in bf16
// (what training under --precision bf16 runs its matrix products in: on CPUs with bf16 dot
// products oneDNN's bf16 kernels run at several times float32's rate).
BenchCase matmul_case(int64_t n, torch::Device device, torch::ScalarType dtype = torch::kFloat32) {
  BenchCase c;
  c.name = dtype == torch::kBFloat16 ? "matmul_bf16" : "matmul_f32";
  c.unit = "GFLOP/s";
  c.params = std::to_string(n) + "x" + std::to_string(n) + "x" + std::to_string(n);
  c.run_once = [n, device, dtype] {
    torch::NoGradGuard no_grad;
    const auto options = torch::TensorOptions().device(device).dtype(dtype);
    const auto a = torch::randn({n, n}, options);  // [n, n]
    const auto b = torch::randn({n, n}, options);  // [n, n]
    // Enough multiplies that one run lasts ~0.5 s on a laptop core.
    const int iters = std::max<int>(1, static_cast<int>(2e9 / (2.0 * n * n * n)));
    if (device.is_cuda()) torch::cuda::synchronize();
    const auto start = std::chrono::steady_clock::now();
    for (int i = 0; i < iters; ++i) (void)torch::mm(a, b);
    if (device.is_cuda()) torch::cuda::synchronize();
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return 2.0 * n * n * n * iters / seconds / 1e9;
  };
  return c;
}

// A scratch directory for generated inputs, removed at exit.
const std::filesystem::path& scratch_dir() {
  static const std::filesystem::path dir = [] {
    auto d = std::filesystem::temp_directory_path() / ("dojo_bench_" + std::to_string(::getpid()));
    std::filesystem::create_directories(d);
    std::atexit([] {
      std::error_code ec;
      std::filesystem::remove_all(
          std::filesystem::temp_directory_path() / ("dojo_bench_" + std::to_string(::getpid())), ec);
    });
    return d;
  }();
  return dir;
}

// A 64x64, 96-frame H.264 clip of moving gradients (the size DojoSim episodes use).
std::string synthetic_clip() {
  const auto path = (scratch_dir() / "synthetic_64.mp4").string();
  if (std::filesystem::exists(path)) return path;
  auto t = torch::arange(96).view({96, 1, 1, 1});
  auto y = torch::arange(64).view({1, 64, 1, 1});
  auto x = torch::arange(64).view({1, 1, 64, 1});
  auto c = torch::arange(3).view({1, 1, 1, 3});
  const auto frames = ((x * 4 + t * 3 + c * 40) % 256 + (y * 2) % 64).clamp(0, 255).to(torch::kUInt8);
  io::VideoWriterOptions options;
  options.fps = 10;
  options.keyframe_interval = 8;
  io::write_video(path, frames, options);
  return path;
}

// `path` is resolved on first run so that --list generates nothing.
// Parquet decoding of a LeRobot-shaped table: 100k rows of list<float>[44] `action` plus
// `timestamp` and `episode_index`, 2000-row pages, snappy; values decoded per second.
BenchCase parquet_case() {
  BenchCase c;
  c.name = "parquet_decode";
  c.unit = "Mvalues/s";
  c.params = "100k rows x (44-float list + 2 scalars), snappy, 2000-row pages";
  c.run_once = [] {
    static const std::string bytes = [] {
      io::ParquetWriteOptions options;
      options.codec = io::ParquetCodec::kSnappy;
      options.rows_per_page = 2000;
      io::ParquetWriter writer(options);
      std::vector<std::optional<std::vector<float>>> action;
      std::vector<float> timestamp;
      std::vector<int64_t> episode;
      for (int i = 0; i < 100000; ++i) {
        std::vector<float> row(44);
        for (int d = 0; d < 44; ++d) row[d] = 0.001f * i + d;
        action.push_back(std::move(row));
        timestamp.push_back(i / 20.f);
        episode.push_back(i / 500);
      }
      writer.add_list_f32("action", action);
      writer.add_f32("timestamp", timestamp);
      writer.add_i64("episode_index", episode);
      return writer.to_bytes();
    }();
    const auto start = std::chrono::steady_clock::now();
    const auto file = io::ParquetFile::from_buffer(bytes, "bench.parquet");
    const auto action = file.read_list_f32("action");
    const auto timestamp = file.read_f32("timestamp");
    const auto episode = file.read_i64("episode_index");
    const double values = static_cast<double>(action.values.size() + timestamp.size() + episode.size());
    return values / 1e6 / seconds_since(start);
  };
  return c;
}

BenchCase decode_case(const std::string& name, std::function<std::string()> path, const std::string& params) {
  BenchCase c;
  c.name = name;
  c.unit = "frames/s";
  c.params = params;
  c.run_once = [path] {
    const std::string file = path();
    const auto start = std::chrono::steady_clock::now();
    io::VideoReader reader(file);
    const auto frames = reader.read_all();  // [N, H, W, 3]
    return frames.size(0) / seconds_since(start);
  };
  return c;
}

#ifdef DOJO_WITH_SIM
BenchCase sim_case(const std::string& embodiment, int size, bool render) {
  BenchCase c;
  c.name = std::string("sim_") + (render ? "render_" : "physics_") + embodiment;
  c.unit = "steps/s";
  c.params = std::string(render ? std::to_string(size) + "x" + std::to_string(size) : "no rendering") +
             ", 48-step episode incl. world build";
  c.run_once = [embodiment, size, render] {
    sim::SceneSampling sampling;
    sampling.width = size;
    sampling.height = size;
    const auto emb = sim::parse_embodiment(embodiment);
    sim::EpisodeSpec spec;
    spec.scene = sim::sample_scene(emb, sampling, 1);
    spec.controller = sim::default_controller(emb);
    spec.num_steps = 48;
    spec.render = render;
    const auto start = std::chrono::steady_clock::now();
    (void)sim::run_episode(spec);
    return spec.num_steps / seconds_since(start);
  };
  return c;
}

BenchCase loader_case(int workers) {
  BenchCase c;
  c.name = "clip_loader";
  c.unit = "clips/s";
  c.params = "robot 64x64, 13 frames, batch 4, " + std::to_string(workers) + " workers";
  c.run_once = [workers] {
    const auto dir = scratch_dir() / "robot_dataset";
    if (!std::filesystem::exists(dir / "info.json")) {
      sim::GenerateOptions options;
      options.embodiment = "robot";
      options.episodes = 4;
      options.workers = 2;
      (void)sim::generate_dataset(dir, options);
    }
    auto mixture = std::make_shared<data::ClipMixture>();
    mixture->add(
        std::make_shared<data::ClipDataset>(data::EpisodeStore::open(dir), data::ClipConfig{}, "all"), 1.0);
    data::LoaderOptions options;
    options.batch_size = 4;
    options.workers = workers;
    data::PrefetchLoader loader(mixture, options);
    const auto start = std::chrono::steady_clock::now();
    constexpr int kBatches = 16;
    for (int i = 0; i < kBatches; ++i) (void)loader.next();
    return kBatches * options.batch_size / seconds_since(start);
  };
  return c;
}
#endif

}  // namespace

void register_case_factory(std::function<std::vector<BenchCase>(const BenchOptions&)> factory) {
  factories().push_back(std::move(factory));
}

std::vector<BenchCase> builtin_cases(const BenchOptions& options) {
  const torch::Device device = parse_device(options.device);
  std::vector<BenchCase> cases;
  cases.push_back(matmul_case(1024, device));
  cases.push_back(matmul_case(1024, device, torch::kBFloat16));
  if (!options.video_path.empty()) {
    const std::string path = options.video_path;
    const auto info = io::probe_video(path);
    cases.push_back(decode_case(
        "video_decode", [path] { return path; },
        std::filesystem::path(path).filename().string() + " " + info.codec + " " +
            std::to_string(info.width) + "x" + std::to_string(info.height)));
  } else {
    cases.push_back(decode_case("video_decode", synthetic_clip, "synthetic h264 64x64, 96 frames"));
    const std::string camera_clip = "/usr/share/doc/opencv-doc/examples/data/vtest.avi";
    if (std::filesystem::exists(camera_clip))
      cases.push_back(decode_case(
          "video_decode_camera", [camera_clip] { return camera_clip; },
          "opencv-doc vtest.avi msmpeg4v3 768x576"));
  }
  cases.push_back(parquet_case());
#ifdef DOJO_WITH_SIM
  cases.push_back(sim_case("robot", 64, true));
  cases.push_back(sim_case("human", 64, true));
  cases.push_back(sim_case("robot", 64, false));
  cases.push_back(loader_case(2));
#endif
  for (const auto& factory : factories()) {
    auto more = factory(options);
    cases.insert(cases.end(), more.begin(), more.end());
  }
  if (options.only.empty()) return cases;
  std::vector<BenchCase> selected;
  for (const auto& name : options.only) {
    bool found = false;
    for (auto& c : cases)
      if (c.name == name) {
        selected.push_back(c);
        found = true;
      }
    if (!found) throw UsageError("--only: no benchmark row named '" + name + "' (see dojo bench --list)");
  }
  return selected;
}

std::vector<BenchRow> run_cases(const std::vector<BenchCase>& cases, const BenchOptions& options) {
  std::vector<BenchRow> rows;
  for (const auto& c : cases) {
    LOG_INFO("bench ", c.name, " (", c.params, "): ", options.warmup, " warm-up + ", options.repeats,
             " repeats");
    for (int i = 0; i < options.warmup; ++i) (void)c.run_once();
    std::vector<double> values;
    for (int i = 0; i < std::max(1, options.repeats); ++i) values.push_back(c.run_once());
    double mean = 0;
    for (double v : values) mean += v;
    mean /= values.size();
    double var = 0;
    for (double v : values) var += (v - mean) * (v - mean);
    // Sample standard deviation; zero for a single repeat.
    const double stddev = values.size() > 1 ? std::sqrt(var / (values.size() - 1)) : 0.0;
    rows.push_back({c.name, c.unit, c.params, mean, stddev, static_cast<int>(values.size())});
  }
  return rows;
}

std::string to_markdown(const std::vector<BenchRow>& rows, const BenchOptions& options) {
  std::ostringstream out;
  const std::time_t now = std::time(nullptr);
  char date[32];
  std::strftime(date, sizeof date, "%Y-%m-%d", std::gmtime(&now));
  out << "commit " << git_commit() << ", " << date << ", device " << options.device << ", threads "
      << threads() << ", BLAS " << blas_library() << ", torch " << torch_version() << "\n\n";
  out << "| benchmark | params | value | unit | repeats |\n|---|---|---|---|---|\n";
  for (const auto& row : rows) {
    char value[64];
    std::snprintf(value, sizeof value, "%.2f ± %.2f", row.mean, row.stddev);
    out << "| " << row.name << " | " << row.params << " | " << value << " | " << row.unit << " | "
        << row.repeats << " |\n";
  }
  return out.str();
}

nlohmann::json to_json(const std::vector<BenchRow>& rows, const BenchOptions& options) {
  nlohmann::json j;
  j["commit"] = git_commit();
  j["device"] = options.device;
  j["threads"] = threads();
  j["blas"] = blas_library();
  j["torch_version"] = torch_version();
  j["rows"] = nlohmann::json::array();
  for (const auto& row : rows)
    j["rows"].push_back({{"name", row.name},
                         {"params", row.params},
                         {"mean", row.mean},
                         {"std", row.stddev},
                         {"unit", row.unit},
                         {"repeats", row.repeats}});
  return j;
}

}  // namespace dojo::bench
