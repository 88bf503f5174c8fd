#include "core/checkpoint.h"

#include <signal.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <fstream>
#include <sstream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"

namespace dojo {
namespace fs = std::filesystem;

namespace {

constexpr const char* kConfigFile = "config.json";
constexpr const char* kModelFile = "model.safetensors";
constexpr const char* kAdapterFile = "adapter_model.safetensors";
constexpr const char* kTrainerJsonFile = "trainer_state.json";
constexpr const char* kTrainerTensorsFile = "trainer_state.safetensors";
constexpr const char* kOldSuffix = ".dojo-old";
constexpr const char* kTempSuffix = ".dojo-tmp-";

// Absolute, normalised, without a trailing separator, so that siblings can be formed.
fs::path normalise(const fs::path& dir) {
  fs::path path = fs::absolute(dir).lexically_normal();
  if (path.filename().empty()) path = path.parent_path();
  DOJO_CHECK(!path.filename().empty() && path.filename() != "..",
             "'" + dir.string() + "' cannot be a checkpoint directory");
  return path;
}

fs::path sibling(const fs::path& dir, const std::string& suffix) {
  return dir.parent_path() / (dir.filename().string() + suffix);
}

bool path_exists(const fs::path& path) {
  std::error_code ec;
  return fs::exists(fs::symlink_status(path, ec));
}

void rename_path(const fs::path& from, const fs::path& to) {
  std::error_code ec;
  fs::rename(from, to, ec);
  if (ec) throw Error("cannot rename " + from.string() + " to " + to.string() + ": " + ec.message());
}

void remove_tree(const fs::path& path) {
  std::error_code ec;
  fs::remove_all(path, ec);
  if (ec) throw Error("cannot remove " + path.string() + ": " + ec.message());
}

// Brings DIR back to "DIR is the checkpoint" after an interrupted save (see checkpoint.h) and
// removes temporaries of processes that no longer run.
void repair(const fs::path& dir) {
  const fs::path old = sibling(dir, kOldSuffix);
  if (path_exists(old)) {
    if (path_exists(dir)) {
      remove_tree(old);
    } else {
      LOG_WARN("an earlier save of ", dir.string(), " was interrupted; restoring the previous checkpoint");
      rename_path(old, dir);
    }
    fsync_directory(dir.parent_path());
  }
  std::error_code ec;
  const std::string temp_prefix = dir.filename().string() + kTempSuffix;
  for (const auto& entry : fs::directory_iterator(dir.parent_path(), ec)) {
    const std::string name = entry.path().filename().string();
    if (name.compare(0, temp_prefix.size(), temp_prefix) != 0) continue;
    const std::string pid_text = name.substr(temp_prefix.size());
    if (pid_text.empty() || pid_text.find_first_not_of("0123456789") != std::string::npos) continue;
    const pid_t pid = static_cast<pid_t>(std::stol(pid_text));
    if (pid == ::getpid() || (::kill(pid, 0) != 0 && errno == ESRCH)) remove_tree(entry.path());
  }
}

void check_replaceable(const fs::path& dir) {
  if (!path_exists(dir)) return;
  DOJO_CHECK(fs::is_directory(dir),
             "cannot save a checkpoint to " + dir.string() + ": it is not a directory");
  if (fs::is_empty(dir) || path_exists(dir / kConfigFile) || path_exists(dir / kModelFile)) return;
  throw Error("refusing to replace " + dir.string() +
              ": it is a non-empty directory that is not a checkpoint (no config.json or model.safetensors)");
}

}  // namespace

void save_checkpoint(const fs::path& dir_in, const CheckpointData& data) {
  const fs::path dir = normalise(dir_in);
  {
    std::error_code ec;
    fs::create_directories(dir.parent_path(), ec);
    if (ec) throw Error("cannot create " + dir.parent_path().string() + ": " + ec.message());
  }
  repair(dir);
  check_replaceable(dir);

  const fs::path temp = sibling(dir, kTempSuffix + std::to_string(::getpid()));
  remove_tree(temp);
  {
    std::error_code ec;
    fs::create_directory(temp, ec);
    if (ec) throw Error("cannot create " + temp.string() + ": " + ec.message());
  }
  try {
    write_file_atomic(temp / kConfigFile, data.config.dump(2) + "\n");
    Metadata metadata = data.model_metadata;
    if (metadata.count("config") == 0) metadata["config"] = data.config.dump();
    if (data.model_stream)
      save_safetensors(temp / kModelFile, *data.model_stream, metadata);
    else
      save_safetensors(temp / kModelFile, data.model, metadata);
    if (!data.adapter.empty()) save_safetensors(temp / kAdapterFile, data.adapter, data.adapter_metadata);
    if (data.trainer) {
      save_safetensors(temp / kTrainerTensorsFile, data.trainer->tensors);
      const nlohmann::json state = {{"step", data.trainer->step}, {"extra", data.trainer->extra}};
      write_file_atomic(temp / kTrainerJsonFile, state.dump(2) + "\n");
    }
    fsync_directory(temp);
  } catch (...) {
    std::error_code ec;
    fs::remove_all(temp, ec);
    throw;
  }
  crash_point("ckpt:staged");

  const fs::path old = sibling(dir, kOldSuffix);
  if (path_exists(dir)) {
    rename_path(dir, old);
    crash_point("ckpt:old-moved");
  }
  rename_path(temp, dir);
  fsync_directory(dir.parent_path());
  crash_point("ckpt:new-in-place");
  if (path_exists(old)) {
    remove_tree(old);
    fsync_directory(dir.parent_path());
  }
  crash_point("ckpt:done");
}

fs::path resolve_checkpoint_dir(const fs::path& dir_in) {
  const fs::path dir = normalise(dir_in);
  if (path_exists(dir)) return dir;
  const fs::path old = sibling(dir, kOldSuffix);
  if (path_exists(old)) {
    LOG_WARN("a save of ", dir.string(), " was interrupted; reading the previous checkpoint ", old.string());
    return old;
  }
  throw Error(dir_in.string() + ": no such checkpoint directory");
}

bool checkpoint_exists(const fs::path& dir_in) {
  const fs::path dir = normalise(dir_in);
  return path_exists(dir) || path_exists(sibling(dir, kOldSuffix));
}

Checkpoint Checkpoint::open(const fs::path& dir_in) {
  Checkpoint ckpt;
  ckpt.dir_ = resolve_checkpoint_dir(dir_in);
  DOJO_CHECK(fs::is_directory(ckpt.dir_), ckpt.dir_.string() + ": not a checkpoint directory");
  for (const char* required : {kConfigFile, kModelFile})
    DOJO_CHECK(path_exists(ckpt.dir_ / required),
               (ckpt.dir_ / required).string() + ": missing (not a checkpoint directory?)");
  ckpt.config_ = read_json_file(ckpt.dir_ / kConfigFile);
  ckpt.model_ = SafetensorsFile::open(ckpt.dir_ / kModelFile);
  if (path_exists(ckpt.dir_ / kAdapterFile)) ckpt.adapter_ = SafetensorsFile::open(ckpt.dir_ / kAdapterFile);
  if (path_exists(ckpt.dir_ / kTrainerJsonFile)) {
    const fs::path json_path = ckpt.dir_ / kTrainerJsonFile;
    nlohmann::json state = read_json_file(json_path);
    DOJO_CHECK(state.is_object() && state.contains("step") && state["step"].is_number_integer(),
               json_path.string() + ": no integer \"step\"");
    if (!state.contains("extra")) state["extra"] = nlohmann::json::object();
    ckpt.trainer_json_ = std::move(state);
    ckpt.trainer_tensors_ = SafetensorsFile::open(ckpt.dir_ / kTrainerTensorsFile);
  }
  return ckpt;
}

int64_t Checkpoint::step() const {
  DOJO_CHECK(trainer_json_, dir_.string() + ": no trainer state (an inference-only checkpoint)");
  return (*trainer_json_)["step"].get<int64_t>();
}

const nlohmann::json& Checkpoint::trainer_extra() const {
  DOJO_CHECK(trainer_json_, dir_.string() + ": no trainer state (an inference-only checkpoint)");
  return (*trainer_json_)["extra"];
}

const SafetensorsFile& Checkpoint::adapter() const {
  DOJO_CHECK(adapter_, dir_.string() + ": no adapter_model.safetensors (no LoRA adapters)");
  return *adapter_;
}

const SafetensorsFile& Checkpoint::trainer_tensors() const {
  DOJO_CHECK(trainer_tensors_, dir_.string() + ": no trainer state (an inference-only checkpoint)");
  return *trainer_tensors_;
}

NamedTensors capture_rng_state() {
  NamedTensors out;
  auto capture = [&out](const std::string& name, at::Generator generator) {
    std::lock_guard<std::mutex> lock(generator.mutex());
    out.emplace_back(name, generator.get_state());
  };
  capture("rng.cpu", at::globalContext().defaultGenerator(torch::kCPU));
  if (torch::cuda::is_available()) {
    for (size_t i = 0; i < torch::cuda::device_count(); ++i)
      capture("rng.cuda." + std::to_string(i), at::globalContext().defaultGenerator(torch::Device(
                                                   torch::kCUDA, static_cast<c10::DeviceIndex>(i))));
  }
  return out;
}

void restore_rng_state(const NamedTensors& tensors) {
  for (const auto& [name, state] : tensors) {
    torch::Device device(torch::kCPU);
    if (name == "rng.cpu") {
      // the default: CPU
    } else if (name.rfind("rng.cuda.", 0) == 0) {
      const std::string digits = name.substr(9);
      DOJO_CHECK(!digits.empty() && digits.find_first_not_of("0123456789") == std::string::npos,
                 "bad RNG state name '" + name + "'");
      const int index = std::stoi(digits);
      if (!torch::cuda::is_available() || index >= static_cast<int>(torch::cuda::device_count())) {
        LOG_WARN("not restoring ", name, ": no such CUDA device here");
        continue;
      }
      device = torch::Device(torch::kCUDA, static_cast<c10::DeviceIndex>(index));
    } else {
      continue;
    }
    at::Generator generator = at::globalContext().defaultGenerator(device);
    std::lock_guard<std::mutex> lock(generator.mutex());
    generator.set_state(state.to(torch::kUInt8).contiguous());
  }
}

fs::path run_checkpoint(const fs::path& dir) {
  return checkpoint_exists(dir / "checkpoint") ? dir / "checkpoint" : dir;
}

nlohmann::json checkpoint_fingerprint(const fs::path& dir) {
  if (dir.empty()) return nullptr;
  auto weights = resolve_checkpoint_dir(dir) / "model.safetensors";
  if (!fs::exists(weights)) weights = resolve_checkpoint_dir(run_checkpoint(dir)) / "model.safetensors";
  DOJO_CHECK(fs::exists(weights), weights.string() + ": missing (not a checkpoint directory)");
  return {{"path", fs::absolute(dir).lexically_normal().string()},
          {"bytes", static_cast<int64_t>(fs::file_size(weights))},
          {"mtime", static_cast<int64_t>(fs::last_write_time(weights).time_since_epoch().count())}};
}

}  // namespace dojo
