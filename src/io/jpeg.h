// JPEG encoding and decoding of uint8 RGB frames through libjpeg-turbo's TurboJPEG API: the
// server's frame format (browsers decode it natively, and it is ~20x smaller than raw RGB).
#pragma once

#include <ATen/core/Tensor.h>

#include <string>
#include <string_view>

namespace dojo::io {

// frame [H, W, 3] uint8 RGB -> JPEG bytes (4:2:0 chroma, quality 1-100).
std::string encode_jpeg(const at::Tensor& frame, int quality = 85);
// JPEG bytes -> [H, W, 3] uint8 RGB. Corrupt input throws dojo::Error naming `what`.
at::Tensor decode_jpeg(std::string_view bytes, const std::string& what = "JPEG image");

}  // namespace dojo::io
