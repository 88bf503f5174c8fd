#include "models/fast_decoder.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "core/checkpoint.h"
#include "core/error.h"
#include "test_util.h"

namespace dojo::models {
namespace {

FastDecoderConfig small_config() {
  FastDecoderConfig c;
  c.widths = {16, 12, 8};
  c.blocks = {1, 1, 1};
  c.head_width = 8;
  return c;
}

// 1 + 4k frames like the Wan decoder; streaming one latent at a time equals the whole-clip call;
// a latent changes only its own frames and later ones (the memory looks back only).
TEST(FastDecoder, StreamsCausallyWithTheWanFrameCount) {
  test::OneThread one;
  torch::manual_seed(0);
  FastDecoder d(small_config());
  torch::NoGradGuard no_grad;
  const auto z = torch::randn({2, 16, 4, 4, 4});
  const auto all = d->decode(z);
  ASSERT_EQ(all.sizes(), (std::vector<int64_t>{2, 3, 13, 32, 32}));
  FastDecoderState state;
  std::vector<torch::Tensor> parts;
  for (int64_t t = 0; t < 4; ++t) parts.push_back(d->step(z.select(2, t), state));
  EXPECT_EQ(parts[0].size(2), 1);
  EXPECT_EQ(parts[1].size(2), 4);
  EXPECT_TRUE(torch::allclose(torch::cat(parts, 2), all, 1e-5, 1e-6));

  auto z2 = z.clone();
  z2.select(2, 2).add_(1.0);
  const auto changed = d->decode(z2);
  EXPECT_TRUE(changed.narrow(2, 0, 5).equal(all.narrow(2, 0, 5))) << "frames of latents 0 and 1";
  EXPECT_FALSE(changed.narrow(2, 5, 4).equal(all.narrow(2, 5, 4)));
  EXPECT_FALSE(changed.narrow(2, 9, 4).equal(all.narrow(2, 9, 4))) << "the memory carries latent 2 forward";
}

TEST(FastDecoder, LearnsATargetAndRoundTripsItsCheckpoint) {
  test::OneThread one;
  torch::manual_seed(1);
  FastDecoder d(small_config());
  const auto z = torch::randn({2, 16, 2, 4, 4});
  // A target the architecture can express: another decoder's frames.
  torch::manual_seed(2);
  FastDecoder teacher(small_config());
  const auto target = teacher->decode(z).detach();
  torch::optim::Adam opt(d->parameters(), torch::optim::AdamOptions(1e-3));
  const auto loss = [&] { return (d->decode(z) - target).pow(2).mean(); };
  const double before = loss().item<double>();
  for (int i = 0; i < 80; ++i) {
    opt.zero_grad();
    loss().backward();
    opt.step();
  }
  EXPECT_LT(loss().item<double>(), 0.5 * before);

  test::TempDir dir;
  save_checkpoint(dir / "fd", fast_decoder_checkpoint(*d));
  auto loaded = load_fast_decoder(dir / "fd");
  torch::NoGradGuard no_grad;
  EXPECT_TRUE(loaded->decode(z).equal(d->decode(z)));
  EXPECT_THROW(FastDecoderConfig::from_json({{"widths", {1, 2}}}), Error);
}

}  // namespace
}  // namespace dojo::models
