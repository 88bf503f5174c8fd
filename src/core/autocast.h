// Mixed precision: the precision setting of training and inference, and an RAII guard around
// libtorch's autocast. Autocast runs matmul-like ops (linear, matmul, conv) in the lower
// precision and keeps the rest in float32; weights stay float32 ("master weights"). The same
// code serves CUDA (bf16 or fp16) and CPU (bf16), which is how it is tested without a GPU.
#pragma once

#include <c10/core/DeviceType.h>
#include <c10/core/ScalarType.h>

#include <string>

namespace dojo {

enum class Precision { kFloat32, kBFloat16, kFloat16 };
Precision parse_precision(const std::string& text);  // fp32 | bf16 | fp16; throws dojo::UsageError
std::string to_string(Precision precision);
// The autocast dtype of a precision (kFloat for fp32, which means "no autocast").
c10::ScalarType autocast_dtype(Precision precision);
// Throws dojo::UsageError when `precision` cannot run on `device`: fp16 autocast is CUDA-only
// (libtorch's CPU autocast supports bf16 only in 1.13).
void check_precision_supported(Precision precision, c10::DeviceType device);
// Throws dojo::UsageError, naming `trainer`, for a precision no trainer trains in: fp16's 5
// exponent bits underflow small gradients unless the loss is scaled (no trainer scales it); bf16
// has float32's range and is what the release trains in.
void check_training_precision(const std::string& trainer, Precision precision);

// Sets autocast for one device type (CPU or CUDA) to `enabled` with lower-precision `dtype`
// for the guard's scope, like Python's torch.autocast(device, dtype, enabled): enabled = false
// turns autocast off inside an outer autocast region. The previous flag and dtype come back on
// destruction; leaving the outermost region clears autocast's cache of casted weights (it is
// only valid while the weights do not change).
class AutocastGuard {
 public:
  AutocastGuard(c10::DeviceType device, c10::ScalarType dtype, bool enabled = true);
  // Enabled unless precision is fp32.
  AutocastGuard(c10::DeviceType device, Precision precision);
  ~AutocastGuard();
  AutocastGuard(const AutocastGuard&) = delete;
  AutocastGuard& operator=(const AutocastGuard&) = delete;

  // Drops the lower-precision copies of the weights autocast has made in this region. Autocast
  // keeps one copy per weight that requires grad, made even by a pass without gradients; a later
  // pass with gradients would reuse it and the weights would get none. Call it before such a pass.
  static void clear_cache();

  // The current autocast state of a device type (CPU or CUDA).
  static bool is_enabled(c10::DeviceType device);
  static c10::ScalarType dtype(c10::DeviceType device);

 private:
  c10::DeviceType device_;
  bool previous_enabled_;
  c10::ScalarType previous_dtype_;
};

}  // namespace dojo
