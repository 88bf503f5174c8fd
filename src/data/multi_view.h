// Several cameras as one video: each frame of every view is tiled into one canvas (views side by
// side, stacked, or in a grid), the way the release's maintainers suggest feeding a single-view
// model several cameras. Everything downstream (latent caches, training, rollouts, evaluation,
// streaming, the server) sees the canvas as the dataset's frames; the tiling is recorded in the
// world model's checkpoint ("views") so later commands open the data the same way, split the
// canvas back into views for per-view scores and the teleoperation page shows them apart.
//
//   side_by_side: [v0 | v1 | ...]        canvas h x (n w)
//   stack:        v0 over v1 over ...     canvas (n h) x w
//   grid:         ceil(sqrt n) columns    e.g. 2x2 for 3 or 4 views (empty cells black)
#pragma once

#include <ATen/core/Tensor.h>

#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "data/episode_source.h"

namespace dojo::data {

enum class ViewLayout { kSideBySide, kStack, kGrid };
ViewLayout parse_view_layout(const std::string& text);  // side_by_side | stack | grid
std::string to_string(ViewLayout layout);

// Where each of `cameras` sits on the canvas.
struct ViewTiling {
  std::vector<std::string> cameras;  // the first is the main view (its keypoints, its actions' camera)
  ViewLayout layout = ViewLayout::kSideBySide;
  int view_height = 0, view_width = 0;  // one view as stored (the canvas is made at this scale)

  int count() const { return static_cast<int>(cameras.size()); }
  int columns() const;
  int rows() const;
  int canvas_height() const { return rows() * view_height; }
  int canvas_width() const { return columns() * view_width; }
  // Views [N, h, w, 3] u8 (one per camera, each already view_height x view_width) -> [N, H, W, 3].
  at::Tensor tile(const std::vector<at::Tensor>& views) const;
  // View v of a canvas of any scale: dims h_dim and w_dim of `canvas` are the canvas's height and
  // width (e.g. 2 and 3 of [N, 3, H, W], 1 and 2 of [N, H, W, 3]); the crop is proportional.
  at::Tensor crop(const at::Tensor& canvas, int view, int64_t h_dim, int64_t w_dim) const;

  nlohmann::json to_json() const;  // {"cameras", "layout", "view_height", "view_width"}
  static ViewTiling from_json(const nlohmann::json& j, const std::string& where);
};

// The views of one dataset (each opened with its camera) as one source whose frames are the
// canvas; arrays, episodes and statistics are the first view's. Every view must list the same
// episodes with the same frame counts.
class MultiViewSource : public EpisodeSource {
 public:
  MultiViewSource(std::vector<std::shared_ptr<const EpisodeSource>> views, ViewTiling tiling);

  const ViewTiling& tiling() const { return tiling_; }
  std::string format() const override { return views_.front()->format(); }
  const std::filesystem::path& root() const override { return views_.front()->root(); }
  const DatasetInfo& info() const override { return info_; }
  std::string episode_location(size_t index) const override {
    return views_.front()->episode_location(index);
  }
  at::Tensor read_frames(size_t index, const std::vector<int64_t>& frames) const override;  // [N, H, W, 3]
  EpisodeData read_arrays(size_t index) const override { return views_.front()->read_arrays(index); }
  nlohmann::json describe() const override;

 private:
  std::vector<std::shared_ptr<const EpisodeSource>> views_;
  ViewTiling tiling_;
  DatasetInfo info_;
};

// The tiling a world model was trained with (its config's "views"), or none.
std::optional<ViewTiling> views_of_config(const nlohmann::json& config, const std::string& where);

}  // namespace dojo::data
