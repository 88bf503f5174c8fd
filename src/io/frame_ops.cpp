// Crop and resize transforms on uint8 RGB frames (declared in io/frame_ops.h).
#include "io/frame_ops.h"

#include <torch/torch.h>

#include <algorithm>
#include <string>
#include <vector>

#include "core/error.h"

namespace dojo::io {

torch::Tensor as_batch(const at::Tensor& frames, const char* what) {
  DOJO_CHECK(frames.defined() && (frames.dim() == 3 || frames.dim() == 4) && frames.size(-1) == 3,
             std::string(what) + ": expected [H, W, 3] or [T, H, W, 3] RGB frames, got shape " +
                 (frames.defined() ? c10::str(frames.sizes()) : std::string("undefined")));
  return frames.dim() == 3 ? frames.unsqueeze(0) : frames;
}

CropBox center_crop_box(int64_t h, int64_t w, int64_t aspect_w, int64_t aspect_h) {
  DOJO_CHECK(h > 0 && w > 0 && aspect_w > 0 && aspect_h > 0,
             "center_crop_box: sizes and aspect must be positive, got " + std::to_string(h) + "x" +
                 std::to_string(w) + " at " + std::to_string(aspect_w) + ":" + std::to_string(aspect_h));
  CropBox box;
  if (w * aspect_h > h * aspect_w) {  // too wide: keep the height
    box.height = h;
    box.width = std::max<int64_t>(1, (2 * h * aspect_w + aspect_h) / (2 * aspect_h));
  } else {  // too tall (or exact): keep the width
    box.width = w;
    box.height = std::max<int64_t>(1, (2 * w * aspect_h + aspect_w) / (2 * aspect_w));
  }
  box.top = (h - box.height) / 2;
  box.left = (w - box.width) / 2;
  return box;
}

namespace {
torch::Tensor restore_rank(const torch::Tensor& batch, const at::Tensor& like) {
  return like.dim() == 3 ? batch.squeeze(0) : batch;
}
}  // namespace

at::Tensor center_crop(const at::Tensor& frames, int64_t crop_h, int64_t crop_w) {
  auto batch = as_batch(frames, "center_crop");  // [T, H, W, 3]
  const int64_t h = batch.size(1), w = batch.size(2);
  DOJO_CHECK(crop_h > 0 && crop_w > 0 && crop_h <= h && crop_w <= w,
             "center_crop: " + std::to_string(crop_h) + "x" + std::to_string(crop_w) + " does not fit in " +
                 std::to_string(h) + "x" + std::to_string(w));
  const int64_t top = (h - crop_h) / 2, left = (w - crop_w) / 2;
  return restore_rank(batch.slice(1, top, top + crop_h).slice(2, left, left + crop_w), frames);
}

at::Tensor center_crop_aspect(const at::Tensor& frames, int64_t aspect_w, int64_t aspect_h) {
  auto batch = as_batch(frames, "center_crop_aspect");
  const CropBox box = center_crop_box(batch.size(1), batch.size(2), aspect_w, aspect_h);
  return center_crop(frames, box.height, box.width);
}

at::Tensor resize(const at::Tensor& frames, int64_t out_h, int64_t out_w) {
  auto batch = as_batch(frames, "resize");  // [T, H, W, 3]
  DOJO_CHECK(out_h > 0 && out_w > 0, "resize: output size must be positive, got " + std::to_string(out_h) +
                                         "x" + std::to_string(out_w));
  if (batch.size(1) == out_h && batch.size(2) == out_w) return frames;
  const bool shrinking = out_h < batch.size(1) || out_w < batch.size(2);
  auto x = batch.permute({0, 3, 1, 2}).to(torch::kFloat32);  // [T, 3, H, W] float
  namespace F = torch::nn::functional;
  x = F::interpolate(x, F::InterpolateFuncOptions()
                            .size(std::vector<int64_t>{out_h, out_w})
                            .mode(torch::kBilinear)
                            .align_corners(false)
                            .antialias(shrinking));
  auto out = x.round_().clamp_(0, 255).to(torch::kUInt8).permute({0, 2, 3, 1}).contiguous();  // [T, h, w, 3]
  return restore_rank(out, frames);
}

at::Tensor resize_center_crop(const at::Tensor& frames, int64_t out_h, int64_t out_w) {
  DOJO_CHECK(out_h > 0 && out_w > 0, "resize_center_crop: output size must be positive, got " +
                                         std::to_string(out_h) + "x" + std::to_string(out_w));
  return resize(center_crop_aspect(frames, out_w, out_h), out_h, out_w);
}

}  // namespace dojo::io
