#include "core/autocast.h"

#include <ATen/autocast_mode.h>
#include <torch/version.h>

#include "core/error.h"

// libtorch 2.4 replaced the per-device functions (set_enabled / set_cpu_enabled,
// set_autocast_gpu_dtype / set_autocast_cpu_dtype, ...) by ones taking the device type; the old
// names are deprecated there and gone later.
#if TORCH_VERSION_MAJOR > 2 || (TORCH_VERSION_MAJOR == 2 && TORCH_VERSION_MINOR >= 4)
#define DOJO_AUTOCAST_DEVICE_API 1
#else
#define DOJO_AUTOCAST_DEVICE_API 0
#endif

namespace dojo {

Precision parse_precision(const std::string& text) {
  if (text == "fp32") return Precision::kFloat32;
  if (text == "bf16") return Precision::kBFloat16;
  if (text == "fp16") return Precision::kFloat16;
  throw UsageError("unknown precision '" + text + "' (expected fp32, bf16 or fp16)");
}

std::string to_string(Precision precision) {
  switch (precision) {
    case Precision::kFloat32:
      return "fp32";
    case Precision::kBFloat16:
      return "bf16";
    case Precision::kFloat16:
      return "fp16";
  }
  return "?";
}

c10::ScalarType autocast_dtype(Precision precision) {
  switch (precision) {
    case Precision::kBFloat16:
      return c10::ScalarType::BFloat16;
    case Precision::kFloat16:
      return c10::ScalarType::Half;
    case Precision::kFloat32:
      break;
  }
  return c10::ScalarType::Float;
}

void check_precision_supported(Precision precision, c10::DeviceType device) {
  if (precision == Precision::kFloat16 && device != c10::DeviceType::CUDA)
    throw UsageError("precision fp16 needs a CUDA device (on CPU use bf16)");
}

void check_training_precision(const std::string& trainer, Precision precision) {
  if (precision == Precision::kFloat16)
    throw UsageError(trainer + ": precision fp16 is not supported for training (no loss scaling); use bf16");
}

namespace {

void check_device(c10::DeviceType device) {
  if (device != c10::DeviceType::CPU && device != c10::DeviceType::CUDA)
    throw Error("autocast: only CPU and CUDA are supported (got " + c10::DeviceTypeName(device) + ")");
}

void set_enabled(c10::DeviceType device, bool enabled) {
#if DOJO_AUTOCAST_DEVICE_API
  at::autocast::set_autocast_enabled(device, enabled);
#else
  if (device == c10::DeviceType::CUDA)
    at::autocast::set_enabled(enabled);
  else
    at::autocast::set_cpu_enabled(enabled);
#endif
}

void set_dtype(c10::DeviceType device, c10::ScalarType dtype) {
#if DOJO_AUTOCAST_DEVICE_API
  at::autocast::set_autocast_dtype(device, dtype);
#else
  if (device == c10::DeviceType::CUDA)
    at::autocast::set_autocast_gpu_dtype(dtype);
  else
    at::autocast::set_autocast_cpu_dtype(dtype);
#endif
}

}  // namespace

void AutocastGuard::clear_cache() { at::autocast::clear_cache(); }

bool AutocastGuard::is_enabled(c10::DeviceType device) {
  check_device(device);
#if DOJO_AUTOCAST_DEVICE_API
  return at::autocast::is_autocast_enabled(device);
#else
  return device == c10::DeviceType::CUDA ? at::autocast::is_enabled() : at::autocast::is_cpu_enabled();
#endif
}

c10::ScalarType AutocastGuard::dtype(c10::DeviceType device) {
  check_device(device);
#if DOJO_AUTOCAST_DEVICE_API
  return at::autocast::get_autocast_dtype(device);
#else
  return device == c10::DeviceType::CUDA ? at::autocast::get_autocast_gpu_dtype()
                                         : at::autocast::get_autocast_cpu_dtype();
#endif
}

AutocastGuard::AutocastGuard(c10::DeviceType device, c10::ScalarType lower, bool enabled)
    : device_(device), previous_enabled_(is_enabled(device)), previous_dtype_(dtype(device)) {
  if (enabled) {
    if (lower != c10::ScalarType::BFloat16 && lower != c10::ScalarType::Half)
      throw Error(std::string("autocast: the lower precision must be bf16 or fp16 (got ") +
                  c10::toString(lower) + ")");
    // libtorch 1.13 throws from set_autocast_cpu_dtype for anything but bf16; refuse it on every
    // version, before any state changes.
    if (device == c10::DeviceType::CPU && lower != c10::ScalarType::BFloat16)
      throw Error("autocast: on CPU only bf16 is supported");
    set_dtype(device_, lower);
  }
  set_enabled(device_, enabled);
  at::autocast::increment_nesting();
}

AutocastGuard::AutocastGuard(c10::DeviceType device, Precision precision)
    : AutocastGuard(device, autocast_dtype(precision), precision != Precision::kFloat32) {}

AutocastGuard::~AutocastGuard() {
  // As torch.autocast's __exit__: the cast cache lives for the outermost region only.
  if (at::autocast::decrement_nesting() == 0) at::autocast::clear_cache();
  set_enabled(device_, previous_enabled_);
  set_dtype(device_, previous_dtype_);
}

}  // namespace dojo
