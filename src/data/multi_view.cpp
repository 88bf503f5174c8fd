#include "data/multi_view.h"

#include <torch/torch.h>

#include <cmath>

#include "core/error.h"
#include "io/frame_ops.h"

namespace dojo::data {

ViewLayout parse_view_layout(const std::string& text) {
  if (text == "side_by_side") return ViewLayout::kSideBySide;
  if (text == "stack") return ViewLayout::kStack;
  if (text == "grid") return ViewLayout::kGrid;
  throw Error("unknown view layout '" + text + "' (side_by_side, stack, grid)");
}

std::string to_string(ViewLayout layout) {
  switch (layout) {
    case ViewLayout::kSideBySide:
      return "side_by_side";
    case ViewLayout::kStack:
      return "stack";
    case ViewLayout::kGrid:
      return "grid";
  }
  return "?";
}

int ViewTiling::columns() const {
  switch (layout) {
    case ViewLayout::kSideBySide:
      return count();
    case ViewLayout::kStack:
      return 1;
    case ViewLayout::kGrid:
      return static_cast<int>(std::ceil(std::sqrt(static_cast<double>(count()))));
  }
  return 1;
}

int ViewTiling::rows() const { return (count() + columns() - 1) / columns(); }

at::Tensor ViewTiling::tile(const std::vector<at::Tensor>& views) const {
  DOJO_CHECK(static_cast<int>(views.size()) == count(),
             "views: " + std::to_string(views.size()) + " views for " + std::to_string(count()) + " cameras");
  const int64_t n = views.front().size(0);
  auto canvas = torch::zeros({n, canvas_height(), canvas_width(), 3}, torch::kUInt8);  // [N, H, W, 3]
  for (int v = 0; v < count(); ++v) {
    DOJO_CHECK(views[v].size(0) == n && views[v].size(1) == view_height && views[v].size(2) == view_width,
               "views: camera '" + cameras[v] + "' gave frames of another size or count");
    canvas.narrow(1, static_cast<int64_t>(v / columns()) * view_height, view_height)
        .narrow(2, static_cast<int64_t>(v % columns()) * view_width, view_width)
        .copy_(views[v]);
  }
  return canvas;
}

at::Tensor ViewTiling::crop(const at::Tensor& canvas, int view, int64_t h_dim, int64_t w_dim) const {
  DOJO_CHECK(view >= 0 && view < count(), "views: no view " + std::to_string(view));
  const int64_t H = canvas.size(h_dim), W = canvas.size(w_dim);
  DOJO_CHECK(H % rows() == 0 && W % columns() == 0,
             "views: a " + std::to_string(H) + "x" + std::to_string(W) + " canvas does not split into " +
                 std::to_string(rows()) + "x" + std::to_string(columns()) + " views");
  const int64_t h = H / rows(), w = W / columns();
  return canvas.narrow(h_dim, (view / columns()) * h, h).narrow(w_dim, (view % columns()) * w, w);
}

nlohmann::json ViewTiling::to_json() const {
  return {{"cameras", cameras},
          {"layout", to_string(layout)},
          {"view_height", view_height},
          {"view_width", view_width}};
}

ViewTiling ViewTiling::from_json(const nlohmann::json& j, const std::string& where) {
  ViewTiling t;
  try {
    t.cameras = j.at("cameras").get<std::vector<std::string>>();
    t.layout = parse_view_layout(j.at("layout").get<std::string>());
    t.view_height = j.at("view_height").get<int>();
    t.view_width = j.at("view_width").get<int>();
  } catch (const nlohmann::json::exception& e) {
    throw Error(where + ": views: " + e.what());
  }
  DOJO_CHECK(t.count() >= 2 && t.view_height > 0 && t.view_width > 0,
             where + ": views: needs 2 or more cameras and a positive view size");
  return t;
}

MultiViewSource::MultiViewSource(std::vector<std::shared_ptr<const EpisodeSource>> views, ViewTiling tiling)
    : views_(std::move(views)), tiling_(std::move(tiling)) {
  DOJO_CHECK(views_.size() >= 2 && static_cast<int>(views_.size()) == tiling_.count(),
             "views: a multi-view dataset needs one source per camera, 2 or more");
  info_ = views_.front()->info();
  const auto& main = info_;
  for (size_t v = 1; v < views_.size(); ++v) {
    const auto& other = views_[v]->info();
    bool same = other.episodes.size() == main.episodes.size();
    for (size_t i = 0; same && i < main.episodes.size(); ++i)
      same = other.episodes[i].frames == main.episodes[i].frames;
    DOJO_CHECK(same, root().string() + ": camera '" + tiling_.cameras[v] +
                         "' does not have the episodes and frame "
                         "counts of '" +
                         tiling_.cameras[0] + "'");
  }
  if (tiling_.view_height == 0) tiling_.view_height = main.height;
  if (tiling_.view_width == 0) tiling_.view_width = main.width;
  DOJO_CHECK(tiling_.view_height > 0 && tiling_.view_width > 0,
             root().string() + ": the main camera's frame size is unknown; give the views' size");
  info_.height = tiling_.canvas_height();
  info_.width = tiling_.canvas_width();
  info_.cameras = tiling_.cameras;
}

at::Tensor MultiViewSource::read_frames(size_t index, const std::vector<int64_t>& frames) const {
  std::vector<at::Tensor> views;
  for (const auto& source : views_) {
    auto view = source->read_frames(index, frames);  // [N, h, w, 3]
    if (view.size(1) != tiling_.view_height || view.size(2) != tiling_.view_width)
      view = io::resize_center_crop(view, tiling_.view_height, tiling_.view_width);
    views.push_back(view);
  }
  return tiling_.tile(views);  // [N, H, W, 3]
}

nlohmann::json MultiViewSource::describe() const {
  auto j = views_.front()->describe();
  j["height"] = info_.height;
  j["width"] = info_.width;
  j["views"] = tiling_.to_json();
  return j;
}

std::optional<ViewTiling> views_of_config(const nlohmann::json& config, const std::string& where) {
  if (!config.contains("views") || config.at("views").is_null()) return std::nullopt;
  return ViewTiling::from_json(config.at("views"), where);
}

}  // namespace dojo::data
