#include "eval/tokenizer_eval.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "eval/metrics.h"
#include "eval/wm_eval.h"
#include "infer/world_model.h"
#include "synthetic_data.h"
#include "test_util.h"
#include "train/wm_test_fixtures.h"

namespace dojo::eval {
namespace {

// `dojo tokenizer eval` and the tokenizer ceiling of `dojo eval` score the same frames the same:
// one round trip, one metric implementation.
TEST(TokenizerEval, AgreesWithTheWorldModelEvaluationOnTheSameFrames) {
  test::OneThread one;
  test::TempDir tmp;
  test::SyntheticOptions data;
  data.episodes = 2;
  data.frames = 16;
  data.size = 16;
  test::write_synthetic_dataset(tmp / "robot", data);
  torch::manual_seed(0);
  models::WanVae vae(models::WanVaeConfig::tiny());
  vae->eval();

  TokenizerEvalOptions o;
  o.split = "all";
  o.clips = 1;
  o.frames = 13;
  const auto tok = evaluate_tokenizer(vae, tmp / "robot", o);
  ASSERT_EQ(tok.originals.size(), 1u);
  const auto& clip = tok.originals[0];  // [13, 16, 16, 3]

  infer::WorldModel wm(models::ActionDit(train::test_fixtures::tiny_dit(true, 32)), vae);
  const auto ceiling = video_metrics(wm.reconstruct_chunks(clip.unsqueeze(0))[0], clip);
  EXPECT_DOUBLE_EQ(tok.psnr, ceiling.psnr);
  EXPECT_DOUBLE_EQ(tok.ssim, ceiling.ssim);
  EXPECT_TRUE(tok.reconstructions[0].equal(wm.reconstruct_video(clip.unsqueeze(0))[0]));
  EXPECT_LT(tok.psnr, 80.0);  // a random tokenizer does not reproduce the frames
}

TEST(TokenizerEval, BadOptionsNameTheField) {
  test::TempDir tmp;
  test::write_synthetic_dataset(tmp / "robot", {});
  models::WanVae vae(models::WanVaeConfig::tiny());
  TokenizerEvalOptions o;
  o.split = "all";
  o.frames = 12;
  EXPECT_NE(test::error_message([&] { evaluate_tokenizer(vae, tmp / "robot", o); }).find("--frames"),
            std::string::npos);
  o.frames = 13;
  o.split = "nonesuch";
  EXPECT_NE(test::error_message([&] { evaluate_tokenizer(vae, tmp / "robot", o); }).find("nonesuch"),
            std::string::npos);
}

}  // namespace
}  // namespace dojo::eval
