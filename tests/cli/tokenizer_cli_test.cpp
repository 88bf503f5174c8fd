#include <nlohmann/json.hpp>

#include "core/safetensors.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo {
namespace {

TEST(TokenizerCli, TrainEvalEncodeOnGeneratedData) {
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 2;
  g.frames = 16;
  test::write_synthetic_dataset(tmp / "data", g);
  const auto data = (tmp / "data").string(), ckpt = (tmp / "tok").string();

  g.seed = 1;
  test::write_synthetic_dataset(tmp / "data2", g);
  // A weighted mixture (the second dataset unweighted weighs 1), recorded in the trainer state.
  auto r = test::run_dojo("--threads 1 tokenizer train --data " + data + ":3 --data " +
                          (tmp / "data2").string() + " --out " + ckpt +
                          " --steps 3 --batch 1 --frames 5 --size 32 --dim 8 --workers 1 --split all");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "tok" / "model.safetensors"));
  const auto mixture =
      nlohmann::json::parse(test::read_file(tmp / "tok" / "trainer_state.json"))["extra"]["mixture"];
  ASSERT_EQ(mixture.size(), 2u) << mixture.dump();
  EXPECT_EQ(mixture[0].at("data"), data);
  EXPECT_EQ(mixture[0].at("weight"), 3.0);
  EXPECT_EQ(mixture[1].at("weight"), 1.0);

  r = test::run_dojo("--threads 1 tokenizer eval --ckpt " + ckpt + " --data " + data +
                     " --split all --clips 2 --frames 5 --json" + " --video " + (tmp / "cmp.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto j = nlohmann::json::parse(r.output.substr(r.output.find('{')));
  EXPECT_GT(j.at("psnr").get<double>(), 0.0);
  EXPECT_GT(j.at("ssim").get<double>(), -1.0);
  EXPECT_TRUE(std::filesystem::exists(tmp / "cmp.mp4"));

  r = test::run_dojo("--threads 1 tokenizer encode --ckpt " + ckpt + " --data " + data + " --out " +
                     (tmp / "lat").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto index = nlohmann::json::parse(test::read_file(tmp / "lat" / "index.json"));
  ASSERT_EQ(index.at("episodes").size(), 2u);
  const auto id = index["episodes"][0]["id"].get<std::string>();
  const auto z = SafetensorsFile::open(tmp / "lat" / (id + ".safetensors")).tensor("z");
  EXPECT_EQ(z.sizes(), (std::vector<int64_t>{16, 4, 4, 4}));  // 16 frames -> 13 used -> 4 latents

  r = test::run_dojo("--threads 1 tokenizer train --data " + data + " --out " + ckpt + " --frames 6");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("--frames"), std::string::npos) << r.output;
}

}  // namespace
}  // namespace dojo
