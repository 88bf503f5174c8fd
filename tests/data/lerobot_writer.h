// Writes small LeRobot datasets (v2.1 and v3.0) with the project's own Parquet and video writers,
// laid out as GR-1's public set: 44-d raw actions and states, meta/modality.json, stats.json, an
// ego-view camera. Shared by the reader tests and the tests that roll models out on LeRobot data.
#pragma once

#include <ATen/core/Tensor.h>

#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "io/parquet_writer.h"

namespace dojo::data::lerobot_fixture {

constexpr int kRawDim = 44;  // GR-1 state/action as stored
constexpr double kFps = 20;
extern const char* const kCamera;
extern const std::vector<std::string> kTasks;

// The raw action of dimension `dim` at frame `row` of episode `episode`.
float raw_action(int episode, int64_t row, int dim);

struct Fixture {
  int episodes = 2;
  int64_t frames = 30;
  bool v3 = false;
  int raw_dim = kRawDim;
  std::string robot_type = "fourier_gr1_arms_waist";
  bool modality = true;  // write GR-1's meta/modality.json
};

// Grey level of the frame at global frame number g (episodes back to back).
int level(int64_t g);
// Frames of grey level 10 + 4 g for global frame numbers g = first .. first + count - 1: [count, 32, 32, 3].
at::Tensor grey_frames(int64_t first, int64_t count);
void write_json(const std::filesystem::path& path, const nlohmann::json& j);
nlohmann::json gr1_modality();
// Rows of episodes [first, last) as a parquet table.
io::ParquetWriter data_table(const Fixture& fx, int first, int last, const io::ParquetWriteOptions& options);
// The whole dataset under `root`; returns root.
std::filesystem::path make_lerobot(const std::filesystem::path& root, const Fixture& fx = {});

}  // namespace dojo::data::lerobot_fixture
