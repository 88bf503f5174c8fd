#include "models/wan_vae.h"

#include <torch/torch.h>

#include <fstream>
#include <sstream>

#include "core/safetensors.h"
#include "core/state_dict.h"
#include "test_util.h"

namespace dojo::models {
namespace {

std::filesystem::path golden(const std::string& name) { return test::golden_dir() / name; }

// The tiny fixture model with its weights loaded strictly.
WanVae load_fixture_model() {
  const auto weights = SafetensorsFile::open(golden("wan21_vae_tiny_weights.safetensors"));
  const auto config = WanVaeConfig::from_json(nlohmann::json::parse(weights.metadata().at("config")));
  WanVae vae(config);
  const auto report = load_state_dict(*vae, weights);
  EXPECT_TRUE(report.ok()) << report.to_string();
  vae->eval();
  return vae;
}

#define REQUIRE_GOLDEN() \
  ASSERT_TRUE(std::filesystem::exists(golden("wan21_vae_tiny_io.safetensors"))) << "golden fixture missing"

TEST(WanVae, GoldenParity) {
  REQUIRE_GOLDEN();
  torch::NoGradGuard no_grad;
  auto vae = load_fixture_model();
  const auto io = SafetensorsFile::open(golden("wan21_vae_tiny_io.safetensors"));
  const auto x = io.tensor("x");  // [1, 3, 9, 32, 48]

  // The fixture's constants are the published ones our config carries by default.
  const auto mean = io.tensor("latent_mean"), stdv = io.tensor("latent_std");
  for (int64_t c = 0; c < 16; ++c) {
    EXPECT_NEAR(mean[c].item<double>(), vae->config().latent_mean[c], 1e-6);
    EXPECT_NEAR(stdv[c].item<double>(), vae->config().latent_std[c], 1e-6);
  }

  const auto head = vae->encode_head(x);
  EXPECT_LE(test::max_abs(head, io.tensor("enc_head_out")), 1e-5);
  const auto enc = vae->encode(x);
  EXPECT_LE(test::max_abs(enc.mu, io.tensor("mu")), 1e-5);
  EXPECT_LE(test::max_abs(enc.log_var, io.tensor("log_var")), 1e-5);
  const auto z = vae->encode_latents(x);
  EXPECT_LE(test::max_abs(z, io.tensor("z")), 1e-5);

  const auto dec = vae->decode(io.tensor("mu"));
  EXPECT_LE(test::max_abs(dec, io.tensor("x_dec_from_mu")), 1e-4);
  const auto pub = vae->decode_latents(io.tensor("z"));
  EXPECT_LE(test::max_abs(pub, io.tensor("x_dec_published")), 1e-4);
}

TEST(WanVae, WholeClipEqualsChunkedOnFixture) {
  REQUIRE_GOLDEN();
  torch::NoGradGuard no_grad;
  auto vae = load_fixture_model();
  const auto io = SafetensorsFile::open(golden("wan21_vae_tiny_io.safetensors"));
  const auto x = io.tensor("x");
  EXPECT_LE(test::max_abs(vae->encode_head(x, /*chunked=*/false), io.tensor("enc_head_out")), 1e-5);
  EXPECT_LE(test::max_abs(vae->decode(io.tensor("mu"), /*chunked=*/false), io.tensor("x_dec_from_mu")), 1e-4);
}

TEST(WanVae, StreamingEqualsWholeClip) {
  torch::NoGradGuard no_grad;
  torch::manual_seed(3);
  auto cfg = WanVaeConfig::tiny();
  WanVae vae(cfg);
  vae->eval();
  // Non-trivial gains so every norm matters; 17 frames -> 5 latents, batch 2.
  for (auto& p : vae->named_parameters())
    if (p.key().find("gamma") != std::string::npos) p.value().normal_(1.0, 0.2);
  const auto x = torch::rand({2, 3, 17, 16, 24}) * 2 - 1;

  const auto mu_whole = vae->encode(x, false).mu;  // [2, 16, 5, 2, 3]
  ASSERT_EQ(mu_whole.sizes(), (std::vector<int64_t>{2, 16, 5, 2, 3}));
  EXPECT_LE(test::max_abs(vae->encode(x, true).mu, mu_whole), 1e-5);

  // Frames arrive in uneven groups; latents come out when their chunk completes.
  WanVaeStreamEncoder enc(vae);
  std::vector<torch::Tensor> mus;
  int64_t t = 0;
  for (int64_t n : {1, 2, 3, 1, 6, 4}) {
    mus.push_back(enc.push(x.narrow(2, t, n)));
    t += n;
  }
  EXPECT_EQ(mus[0].size(2), 1);
  EXPECT_EQ(mus[1].size(2), 0);
  EXPECT_LE(test::max_abs(torch::cat(mus, 2), mu_whole), 1e-5);

  const auto dec_whole = vae->decode(mu_whole, false);  // [2, 3, 17, 16, 24]
  ASSERT_EQ(dec_whole.sizes(), x.sizes());
  WanVaeStreamDecoder dec(vae);
  std::vector<torch::Tensor> frames;
  int64_t cache_bytes = -1;
  for (int64_t i = 0; i < mu_whole.size(2); ++i) {
    frames.push_back(dec.push(mu_whole.narrow(2, i, 1)));
    EXPECT_EQ(frames.back().size(2), i == 0 ? 1 : 4);
    // Bounded memory: after the first two steps the cache no longer grows.
    if (i >= 2) {
      if (cache_bytes >= 0) {
        EXPECT_EQ(dec.cache().bytes(), cache_bytes);
      }
      cache_bytes = dec.cache().bytes();
    }
  }
  EXPECT_LE(test::max_abs(torch::cat(frames, 2), dec_whole), 1e-4);
  EXPECT_LE(test::max_abs(vae->decode(mu_whole, true), dec_whole), 1e-4);
}

TEST(WanVae, SingleFrameShortcutEqualsConv3dReference) {
  torch::manual_seed(5);
  for (auto stride : {std::vector<int64_t>{1, 1, 1}, std::vector<int64_t>{2, 1, 1}}) {
    CausalConv3d conv(4, 6, std::vector<int64_t>{3, 3, 3}, stride,
                      std::vector<int64_t>{stride[0] == 1 ? 1 : 0, 1, 1});
    const auto cache = torch::randn({2, 4, 2, 6, 7});
    for (const auto& [x, c] : {std::pair{torch::randn({2, 4, 1, 6, 7}), torch::Tensor()},
                               std::pair{torch::randn({2, 4, 5, 6, 7}), torch::Tensor()},
                               std::pair{torch::randn({2, 4, 1, 6, 7}), cache}}) {
      if (stride[0] == 2 && x.size(2) == 1) continue;  // a strided, unpadded time conv needs 3 frames
      const auto fast = conv->forward(x, c);
      conv3d_reference_path() = true;
      const auto ref = conv->forward(x, c);
      conv3d_reference_path() = false;
      EXPECT_LE(test::max_abs(fast, ref), 1e-5);
    }
  }
}

TEST(WanVae, FrameByFrameInitActsPerFrame) {
  // After init_frame_by_frame the model is an image autoencoder applied to the frames it keeps:
  // latent 1 of frames 0..4 encodes frame 4 alone (each temporal downsample keeps the later frame
  // of a pair), and decoding it repeats one image for frames 1..4.
  torch::manual_seed(11);
  torch::NoGradGuard no_grad;
  WanVae vae(WanVaeConfig::tiny());
  init_frame_by_frame(vae);
  vae->eval();
  const auto clip = torch::rand({2, 3, 5, 16, 16}) * 2 - 1;  // [B, 3, T, H, W]
  const auto mu = vae->encode(clip, false).mu;               // [B, z, 2, 2, 2]
  EXPECT_LE(test::max_abs(mu.narrow(2, 0, 1), vae->encode(clip.narrow(2, 0, 1), false).mu), 1e-5);
  EXPECT_LE(test::max_abs(mu.narrow(2, 1, 1), vae->encode(clip.narrow(2, 4, 1), false).mu), 1e-5);
  const auto frames = vae->decode(mu, false);                 // [B, 3, 5, 16, 16]
  const auto image = vae->decode(mu.narrow(2, 1, 1), false);  // [B, 3, 1, 16, 16]
  for (int64_t t = 1; t < 5; ++t)
    EXPECT_LE(test::max_abs(frames.narrow(2, t, 1), image), 1e-5) << "frame " << t;
  // The chunked path agrees (the caches carry zeros through the zeroed past taps).
  EXPECT_LE(test::max_abs(vae->decode(mu, true), frames), 1e-5);
}

TEST(WanVae, FullSizeKeyListMatchesRelease) {
  const auto tsv = test::golden_dir() / "keys" / "wan21_vae_keys.tsv";
  ASSERT_TRUE(std::filesystem::exists(tsv)) << tsv << " is missing";
  std::ifstream in(tsv);
  std::vector<std::pair<std::string, std::string>> expected;
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty()) continue;
    const auto tab = line.find('\t');
    expected.emplace_back(line.substr(0, tab), line.substr(tab + 1));
  }
  ASSERT_EQ(expected.size(), 194u);
  WanVae vae;  // released size: dim 96, z_dim 16
  const auto sd = state_dict(*vae);
  std::vector<std::pair<std::string, std::string>> got;
  int64_t params = 0;
  for (const auto& [name, t] : sd) {
    got.emplace_back(name, shape_string(t.sizes()));
    params += t.numel();
  }
  EXPECT_EQ(got, expected);  // same names, shapes and order
  EXPECT_NEAR(params / 1e6, 126.9, 0.1);
}

TEST(WanVae, ConfigRoundTripAndErrors) {
  auto c = WanVaeConfig::tiny();
  c.attn_scales = {0.25};
  const auto back = WanVaeConfig::from_json(c.to_json());
  EXPECT_EQ(back.to_json(), c.to_json());
  EXPECT_EQ(back.spatial_factor(), 8);
  EXPECT_EQ(back.temporal_factor(), 4);
  EXPECT_NE(test::error_message([] {
              WanVaeConfig::from_json({{"dim", "x"}});
            }).find("'dim'"),
            std::string::npos);
  WanVae vae(WanVaeConfig::tiny());
  EXPECT_NE(test::error_message([&] {
              vae->encode(torch::zeros({1, 3, 6, 16, 16}));
            }).find("1 + 4k"),
            std::string::npos);
  EXPECT_EQ(wan_latent_frames(13), 4);
  EXPECT_EQ(wan_pixel_frames(4), 13);
}

}  // namespace
}  // namespace dojo::models
