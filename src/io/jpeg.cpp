#include "io/jpeg.h"

#include <turbojpeg.h>

#include <memory>

#include "core/error.h"

namespace dojo::io {

namespace {

// One TurboJPEG handle per call: handles are not thread-safe, and creating one costs microseconds.
struct Handle {
  explicit Handle(bool compress) : h(compress ? tjInitCompress() : tjInitDecompress()) {
    DOJO_CHECK(h != nullptr, "JPEG: cannot initialise libjpeg-turbo");
  }
  ~Handle() { tjDestroy(h); }
  Handle(const Handle&) = delete;
  Handle& operator=(const Handle&) = delete;
  tjhandle h;
};

}  // namespace

std::string encode_jpeg(const at::Tensor& frame, int quality) {
  DOJO_CHECK(frame.dim() == 3 && frame.size(2) == 3 && frame.scalar_type() == at::kByte,
             "JPEG: a frame must be [H, W, 3] uint8");
  DOJO_CHECK(quality >= 1 && quality <= 100, "JPEG: quality must be in [1, 100]");
  const auto rgb = frame.contiguous();
  Handle handle(/*compress=*/true);
  unsigned char* out = nullptr;
  unsigned long size = 0;
  const int rc =
      tjCompress2(handle.h, rgb.data_ptr<uint8_t>(), static_cast<int>(rgb.size(1)), 0,
                  static_cast<int>(rgb.size(0)), TJPF_RGB, &out, &size, TJSAMP_420, quality, TJFLAG_FASTDCT);
  std::unique_ptr<unsigned char, void (*)(void*)> owned(
      out, [](void* p) { tjFree(static_cast<unsigned char*>(p)); });
  DOJO_CHECK(rc == 0, std::string("JPEG: encoding failed: ") + tjGetErrorStr2(handle.h));
  return std::string(reinterpret_cast<const char*>(out), size);
}

at::Tensor decode_jpeg(std::string_view bytes, const std::string& what) {
  Handle handle(/*compress=*/false);
  int width = 0, height = 0, subsampling = 0, colorspace = 0;
  const auto* data = reinterpret_cast<const unsigned char*>(bytes.data());
  DOJO_CHECK(!bytes.empty() && tjDecompressHeader3(handle.h, data, bytes.size(), &width, &height,
                                                   &subsampling, &colorspace) == 0,
             what + ": not a JPEG image");
  DOJO_CHECK(
      width > 0 && height > 0 && static_cast<int64_t>(width) * height <= (int64_t{1} << 26),
      what + ": JPEG dimensions " + std::to_string(width) + "x" + std::to_string(height) + " out of range");
  auto out = at::empty({height, width, 3}, at::kByte);
  // A warning (e.g. extra bytes after the image) still yields the whole picture; only fatal
  // errors reject it.
  const int rc = tjDecompress2(handle.h, data, bytes.size(), out.data_ptr<uint8_t>(), width, 0, height,
                               TJPF_RGB, TJFLAG_FASTDCT);
  DOJO_CHECK(rc == 0 || tjGetErrorCode(handle.h) == TJERR_WARNING,
             what + ": corrupt JPEG data (" + tjGetErrorStr2(handle.h) + ")");
  return out;
}

}  // namespace dojo::io
