// Two cameras through the whole chain: `wm train --views ego,side` trains on the tiled canvas and
// records the tiling; `eval` (no --views) reads the data the same way and scores each camera's part;
// the server's capabilities tell the page how to show the cameras apart.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "serve/model_host.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo {
namespace {

TEST(MultiViewCli, TrainsOnTheCanvasAndEvaluatesAndServesEachCamera) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 3;
  g.frames = 52;  // wm stream reads a 49-frame window
  g.val_episodes = 1;
  g.side_camera = true;
  test::write_synthetic_dataset(tmp / "robot", g);
  const auto data = (tmp / "robot").string(), tok = (tmp / "tok").string();
  auto r = test::run_dojo("--threads 1 tokenizer train --data " + data + " --out " + tok +
                          " --steps 1 --batch 1 --frames 5 --size 32 --dim 8 --workers 1 --split all");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo("--threads 1 wm train --stage scratch --steps 2 --views ego,side --data " + data +
                     " --tokenizer " + tok + " --batch 2 --hop 4 --out " + (tmp / "wm").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto checkpoint = tmp / "wm" / "checkpoint";
  const auto config = nlohmann::json::parse(test::read_file(checkpoint / "config.json"));
  EXPECT_EQ(config.at("views").at("cameras"), nlohmann::json::array({"ego", "side"}));
  EXPECT_EQ(config.at("views").at("layout"), "side_by_side");

  r = test::run_dojo("--threads 1 eval --checkpoint " + checkpoint.string() + " --tokenizer " + tok +
                     " --data " + data + " --split val --chunks 1 --steps 2 --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto split = nlohmann::json::parse(r.output.substr(r.output.find("\n{") + 1))["splits"][0];
  EXPECT_NE(split.at("data").get<std::string>().find("32x64"), std::string::npos) << split.at("data");
  for (const char* camera : {"ego", "side"}) {
    const auto& view = split.at("views").at(camera);
    EXPECT_GT(view.at("world_model").at("psnr").get<double>(), 0.0) << camera;
    EXPECT_GT(view.at("copy_frame").at("psnr").get<double>(), 0.0) << camera;
  }
  EXPECT_TRUE(split.at("per_video")[0].at("views").contains("side"));
  // Streamed (the teacher's weights as a student): the canvas, read as trained.
  r = test::run_dojo("--threads 1 wm stream -c " + checkpoint.string() + " --tokenizer " + tok + " --data " +
                     data + " --split val --frames 8 --out " + (tmp / "s.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("32x64"), std::string::npos) << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "s.mp4"));

  serve::ModelHost::Options o;
  serve::ModelSpec model;
  model.name = "teacher";
  model.streaming = false;
  model.checkpoint = checkpoint;
  model.tokenizer = tmp / "tok";
  o.models = {model};
  o.data = tmp / "robot";
  o.split = "val";
  serve::ModelHost host(o);
  host.load();
  const auto caps = host.capabilities();
  EXPECT_EQ(caps.at("views").at("cameras"), nlohmann::json::array({"ego", "side"}));
  EXPECT_EQ(caps.at("frame_height"), 32);
  EXPECT_EQ(caps.at("frame_width"), 64) << "the canvas the model makes";
}

}  // namespace
}  // namespace dojo
