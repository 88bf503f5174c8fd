#include "infer/generator.h"

#include <chrono>
#include <optional>

#include "core/error.h"
#include "core/timing.h"
#include "infer/streaming.h"
#include "infer/world_model.h"

namespace dojo::infer {
namespace {

using Clock = std::chrono::steady_clock;

// Holds `turn` for a scope when there is one.
class Turn {
 public:
  explicit Turn(std::mutex* turn) {
    if (turn) lock_.emplace(*turn);
  }

 private:
  std::optional<std::lock_guard<std::mutex>> lock_;
};

class StudentGenerator : public Generator {
 public:
  StudentGenerator(StreamingEngine engine, std::mutex* turn) : engine_(std::move(engine)), turn_(turn) {}
  torch::Tensor reset(const torch::Tensor& first, uint64_t seed) override {
    Turn turn(turn_);
    return engine_.reset(first.unsqueeze(0), seed)[0];  // [1, H, W, 3]
  }
  int64_t actions_per_step() const override { return engine_.actions_per_step(); }
  torch::Tensor step(const torch::Tensor& actions) override {
    Turn turn(turn_);
    const auto t0 = Clock::now();
    auto frames = engine_.step(actions.unsqueeze(0))[0];  // [4, H, W, 3]
    last_step_seconds_ = seconds_since(t0);
    return frames;
  }

 private:
  StreamingEngine engine_;
  std::mutex* turn_;
};

class TeacherGenerator : public Generator {
 public:
  TeacherGenerator(WorldModel& model, std::mutex* turn, int sampler_steps)
      : model_(model), turn_(turn), sampler_(model.trained_sampler()) {
    if (sampler_steps > 0) sampler_.steps = sampler_steps;
  }
  torch::Tensor reset(const torch::Tensor& first, uint64_t seed) override {
    Turn turn(turn_);
    seed_ = seed;
    chunk_ = 0;
    last_ = model_.reconstruct_frames(first.unsqueeze(0));  // [1, H, W, 3]
    return last_;
  }
  int64_t actions_per_step() const override { return WorldModel::kChunkActions; }
  torch::Tensor step(const torch::Tensor& actions) override {
    Turn turn(turn_);
    const auto t0 = Clock::now();
    const auto video = model_.predict_chunk(last_, actions.unsqueeze(0), seed_ + chunk_++,
                                            sampler_);  // [1, 13, H, W, 3]
    const auto frames = video[0].narrow(0, 1, 12);      // [12, H, W, 3]
    last_ = frames.narrow(0, 11, 1);
    last_step_seconds_ = seconds_since(t0);
    return frames;
  }

 private:
  WorldModel& model_;
  std::mutex* turn_;
  SamplerOptions sampler_;
  torch::Tensor last_;  // [1, H, W, 3]
  uint64_t seed_ = 0;
  int64_t chunk_ = 0;
};

}  // namespace

std::unique_ptr<Generator> make_student_generator(StreamingEngine engine, std::mutex* turn) {
  return std::make_unique<StudentGenerator>(std::move(engine), turn);
}

std::unique_ptr<Generator> make_teacher_generator(WorldModel& model, std::mutex* turn, int sampler_steps) {
  DOJO_CHECK(sampler_steps >= 0, "teacher sampler steps must be >= 0 (0: the trained sampler's)");
  return std::make_unique<TeacherGenerator>(model, turn, sampler_steps);
}

}  // namespace dojo::infer
