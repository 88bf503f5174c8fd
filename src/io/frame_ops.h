// Crop and resize transforms on uint8 RGB frames. io/video.h includes this header, so its users
// get these too.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>

namespace dojo::io {

// Transforms on uint8 RGB frames: [T, H, W, 3] or a single [H, W, 3] (the result keeps the rank).

// Views a [H, W, 3] or [T, H, W, 3] tensor as [T, H, W, 3]; throws dojo::Error naming `what`.
at::Tensor as_batch(const at::Tensor& frames, const char* what);

// Crop rectangle. Offsets are floor((dim - size) / 2): with an odd remainder the extra row or
// column is dropped at the bottom/right.
struct CropBox {
  int64_t top = 0, left = 0, height = 0, width = 0;
};
// The largest centred box of aspect aspect_w:aspect_h inside h x w. The cropped dimension is
// round-half-up(other_dim * ratio); e.g. 720x528 at 4:3 -> 704x528 at left 8.
CropBox center_crop_box(int64_t h, int64_t w, int64_t aspect_w, int64_t aspect_h);

at::Tensor center_crop(const at::Tensor& frames, int64_t crop_h, int64_t crop_w);
at::Tensor center_crop_aspect(const at::Tensor& frames, int64_t aspect_w, int64_t aspect_h);
inline at::Tensor center_crop_4x3(const at::Tensor& frames) { return center_crop_aspect(frames, 4, 3); }
// Bilinear (half-pixel centres, antialiased when shrinking), rounded back to uint8.
at::Tensor resize(const at::Tensor& frames, int64_t out_h, int64_t out_w);
// center_crop_aspect to out_w:out_h, then resize to out_h x out_w.
at::Tensor resize_center_crop(const at::Tensor& frames, int64_t out_h, int64_t out_w);

}  // namespace dojo::io
