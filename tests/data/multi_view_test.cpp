// Several cameras as one canvas: the three layouts tile and crop back exactly, at any scale; a
// dataset's cameras open as one source whose frames are the canvas and whose arrays are the main
// camera's episode's.
#include "data/multi_view.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "data/lerobot_export.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo::data {
namespace {

TEST(MultiView, EachLayoutTilesAndCropsBackExactly) {
  std::vector<at::Tensor> views;
  for (int v = 0; v < 3; ++v) views.push_back(torch::full({2, 8, 12, 3}, 50 * (v + 1), torch::kUInt8));
  for (const auto& [layout, rows, columns] : std::vector<std::tuple<ViewLayout, int, int>>{
           {ViewLayout::kSideBySide, 1, 3}, {ViewLayout::kStack, 3, 1}, {ViewLayout::kGrid, 2, 2}}) {
    ViewTiling t;
    t.cameras = {"ego", "side", "wrist"};
    t.layout = layout;
    t.view_height = 8;
    t.view_width = 12;
    EXPECT_EQ(t.rows(), rows) << to_string(layout);
    EXPECT_EQ(t.columns(), columns) << to_string(layout);
    const auto canvas = t.tile(views);  // [2, 8 rows, 12 columns, 3]
    ASSERT_EQ(canvas.sizes(), (std::vector<int64_t>{2, 8 * rows, 12 * columns, 3}));
    for (int v = 0; v < 3; ++v) EXPECT_TRUE(torch::equal(t.crop(canvas, v, 1, 2), views[v])) << v;
    // A model's frames at another scale, channels first: the crop is proportional.
    const auto model_frames = canvas.permute({0, 3, 1, 2}).repeat_interleave(2, 2).repeat_interleave(2, 3);
    EXPECT_EQ(t.crop(model_frames, 2, 2, 3).sizes(), (std::vector<int64_t>{2, 3, 16, 24}));
    EXPECT_EQ(t.crop(model_frames, 2, 2, 3).min().item<int>(), 150);
    EXPECT_EQ(ViewTiling::from_json(t.to_json(), "x").to_json(), t.to_json());
  }
  EXPECT_NE(test::error_message([] { parse_view_layout("diagonal"); }).find("side_by_side, stack, grid"),
            std::string::npos);
}

TEST(MultiView, ADatasetsCamerasOpenAsOneCanvas) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 2;
  g.frames = 6;
  g.side_camera = true;
  test::write_synthetic_dataset(tmp / "d", g);
  OpenOptions options;
  options.views = {"ego", "side"};
  options.view_layout = "stack";
  const auto canvas_source = open_dataset(tmp / "d", options);
  const auto* tiled = dynamic_cast<const MultiViewSource*>(canvas_source.get());
  ASSERT_NE(tiled, nullptr);
  EXPECT_EQ(canvas_source->info().height, 64);
  EXPECT_EQ(canvas_source->info().width, 32);
  EXPECT_EQ(canvas_source->info().cameras, options.views);
  const auto ego = open_dataset(tmp / "d")->read_frames(1, {0, 3});
  const auto canvas = canvas_source->read_frames(1, {0, 3});
  EXPECT_TRUE(torch::equal(tiled->tiling().crop(canvas, 0, 1, 2), ego));
  // The side camera here mirrors the scene: its part of the canvas is the ego view flipped (as decoded).
  const auto side = tiled->tiling().crop(canvas, 1, 1, 2).to(torch::kFloat);
  EXPECT_LT((side - ego.flip({2}).to(torch::kFloat)).abs().mean().item<double>(), 3.0);
  EXPECT_TRUE(
      torch::equal(canvas_source->read_arrays(1).actions, open_dataset(tmp / "d")->read_arrays(1).actions));
  EXPECT_EQ(canvas_source->describe().at("views").at("layout"), "stack");
  // A camera the dataset did not record.
  options.views = {"ego", "wrist"};
  EXPECT_NE(test::error_message([&] { open_dataset(tmp / "d", options); }).find("no camera 'wrist'"),
            std::string::npos);
}

// A LeRobot set with two observation.images.* features (our exporter writes every camera) reads with
// both views, by modality name.
TEST(MultiView, ALeRobotSetsCamerasTileByName) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 2;
  g.frames = 6;
  g.side_camera = true;
  test::write_synthetic_dataset(tmp / "d", g);
  const auto source = open_dataset(tmp / "d");
  LeRobotExportOptions export_options;
  export_options.robot_type = "dojosim_arm";
  export_lerobot(*source, tmp / "lerobot", export_options);
  OpenOptions options;
  options.embodiment = "none";
  options.views = {"front", "side"};
  const auto lerobot = open_dataset(tmp / "lerobot", options);
  EXPECT_EQ(lerobot->format(), "lerobot-v2.1");
  EXPECT_EQ(lerobot->info().width, 64);
  const auto canvas = lerobot->read_frames(1, {0, 4}).to(torch::kFloat);
  OpenOptions side_only;
  side_only.camera = "side";
  const auto side = open_dataset(tmp / "d", side_only)->read_frames(1, {0, 4}).to(torch::kFloat);
  EXPECT_LT((canvas.narrow(2, 32, 32) - side).abs().mean().item<double>(), 4.0) << "H.264 twice";
  EXPECT_GT((canvas.narrow(2, 0, 32) - side).abs().mean().item<double>(), 1.0)
      << "the front camera is not the side one";
}

}  // namespace
}  // namespace dojo::data
