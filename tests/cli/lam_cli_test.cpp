#include <nlohmann/json.hpp>

#include "core/safetensors.h"
#include "data/episode_store.h"
#include "test_util.h"

#include "synthetic_data.h"

namespace dojo {

TEST(LamCli, TrainLabelProbeEndToEnd) {
  test::TempDir tmp;
  for (const std::string emb : {"human", "robot"}) {
    test::SyntheticOptions o;
    o.embodiment = emb;
    o.episodes = 5;
    o.frames = 12;
    o.size = 48;
    test::write_synthetic_dataset(tmp / emb, o);
  }
  const auto data = " --data " + (tmp / "human").string() + ":1 --data " + (tmp / "robot").string() + ":1";
  auto r = test::run_dojo("lam train --model tiny --steps 4 --batch 2 --save-every 2 --lr 1e-3 --out " +
                          (tmp / "run").string() + data);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "run" / "checkpoint" / "model.safetensors"));
  const auto curve = test::read_file(tmp / "run" / "loss.csv");
  EXPECT_EQ(curve.rfind("step,loss,mse,kl,psnr,grad_norm,clips_per_s\n", 0), 0u) << curve;
  EXPECT_EQ(std::count(curve.begin(), curve.end(), '\n'), 5);

  // Resume: continues to 6 steps, the curve keeps its first rows.
  r = test::run_dojo("lam train --model tiny --steps 6 --batch 2 --save-every 2 --lr 1e-3 --out " +
                     (tmp / "run").string() + data);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto curve2 = test::read_file(tmp / "run" / "loss.csv");
  EXPECT_EQ(std::count(curve2.begin(), curve2.end(), '\n'), 7);
  EXPECT_EQ(curve2.rfind(curve.substr(0, curve.find('\n', curve.find('\n') + 1)), 0), 0u);

  const auto ckpt = (tmp / "run" / "checkpoint").string();
  r = test::run_dojo("lam label --ckpt " + ckpt + " --data " + (tmp / "robot").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto store = data::EpisodeStore::open(tmp / "robot");
  const auto f =
      SafetensorsFile::open(tmp / "robot" / "lam_latents" / (store.info().episodes[0].id + ".safetensors"));
  EXPECT_EQ(f.info("z_mu").shape, (std::vector<int64_t>{store.info().episodes[0].frames - 1, 32}));

  r = test::run_dojo("lam probe --json --ckpt " + ckpt + " --data " + (tmp / "human").string() + " --data " +
                     (tmp / "robot").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto j = nlohmann::json::parse(r.output.substr(r.output.find('{')));
  ASSERT_EQ(j["datasets"].size(), 2u);
  EXPECT_EQ(j["datasets"][0]["target"], "motion_delta");
  EXPECT_EQ(j["datasets"][1]["target"], "action_delta");
  EXPECT_LE(j["datasets"][1]["r2_heldout"].get<double>(), 1.0);

  r = test::run_dojo("lam retrieve --ckpt " + ckpt + " --query " + (tmp / "human").string() + " --data " +
                     (tmp / "robot").string() + " --queries 2 --k 2 --out " + (tmp / "grid.png").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_GT(std::filesystem::file_size(tmp / "grid.png"), 100u);

  r = test::run_dojo("lam train --model tiny --out " + (tmp / "bad").string() + " --data " +
                     (tmp / "missing").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("missing"), std::string::npos) << r.output;
}

}  // namespace dojo
