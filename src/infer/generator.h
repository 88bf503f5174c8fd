// A world model seen from outside: a start frame in, then one step of actions at a time, frames
// out. The server's sessions and closed-loop policy evaluation both drive models through this,
// the real-time student and the teacher alike.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <memory>
#include <mutex>

namespace dojo::infer {

class StreamingEngine;
class WorldModel;

class Generator {
 public:
  virtual ~Generator() = default;
  // first [H, W, 3] uint8 -> the frames to show first [n, H, W, 3] (the start frame as the model sees it).
  virtual torch::Tensor reset(const torch::Tensor& first, uint64_t seed) = 0;
  // Actions one step consumes: 4 (student) or 12 (teacher chunk).
  virtual int64_t actions_per_step() const = 0;
  // actions [actions_per_step(), 384] (the model's layout) -> the next frames [n, H, W, 3] uint8.
  virtual torch::Tensor step(const torch::Tensor& actions) = 0;
  // Seconds the last step computed, not counting a wait for the model's turn.
  double last_step_seconds() const { return last_step_seconds_; }

 protected:
  double last_step_seconds_ = 0;
};

// The student streams one latent frame (4 frames) per step through its KV cache. `turn`, when
// given, is held for every reset and step: generators sharing one network's weights take turns.
std::unique_ptr<Generator> make_student_generator(StreamingEngine engine, std::mutex* turn = nullptr);
// The teacher streams chunk by chunk: 12 actions -> 12 frames, each chunk conditioned on the last
// frame of the one before, sampled with the model's trained sampler (35 steps as released: slow,
// but the quality path) or with `sampler_steps` when > 0. `model` must outlive the generator.
std::unique_ptr<Generator> make_teacher_generator(WorldModel& model, std::mutex* turn = nullptr,
                                                  int sampler_steps = 0);

}  // namespace dojo::infer
