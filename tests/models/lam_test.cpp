#include "models/lam.h"

#include <torch/torch.h>

#include <fstream>
#include <sstream>

#include "core/safetensors.h"
#include "core/state_dict.h"
#include "test_util.h"

namespace dojo::models {

namespace {

struct Golden {
  SafetensorsFile weights, io;
};

// A missing fixture fails the test that asks for it, naming the file: golden tests never skip
// (tests/golden/README.md).
std::optional<Golden> open_golden() {
  const auto dir = test::golden_dir();
  bool present = true;
  for (const auto* name : {"lam_tiny_weights.safetensors", "lam_tiny_io.safetensors"}) {
    if (std::filesystem::exists(dir / name)) continue;
    ADD_FAILURE() << dir / name << " is missing: golden fixtures are never skipped (tests/golden/README.md)";
    present = false;
  }
  if (!present) return std::nullopt;
  return Golden{SafetensorsFile::open(dir / "lam_tiny_weights.safetensors"),
                SafetensorsFile::open(dir / "lam_tiny_io.safetensors")};
}

LatentActionModel golden_model(const Golden& g) {
  const auto config = LamConfig::from_json(nlohmann::json::parse(g.weights.metadata().at("config")));
  LatentActionModel model(config);
  LoadOptions opts;
  opts.prefix = "lam.";
  const auto report = load_state_dict(*model, g.weights, opts);
  EXPECT_TRUE(report.ok()) << report.to_string();
  model->eval();
  return model;
}

}  // namespace

TEST(Lam, TinyConfigMatchesFixtureConfig) {
  auto g = open_golden();
  ASSERT_TRUE(g) << "golden fixture missing from " << test::golden_dir();
  const auto j = nlohmann::json::parse(g->weights.metadata().at("config"));
  const auto c = LamConfig::from_json(j);
  const auto t = LamConfig::tiny();
  EXPECT_EQ(c.model_dim, t.model_dim);
  EXPECT_EQ(c.patch_size, t.patch_size);
  EXPECT_EQ(c.enc_blocks, t.enc_blocks);
  EXPECT_EQ(c.dec_blocks, t.dec_blocks);
  EXPECT_EQ(c.num_heads, t.num_heads);
  EXPECT_EQ(c.latent_dim, t.latent_dim);
}

TEST(Lam, ConfigJsonRoundTripAndErrors) {
  const auto c = LamConfig::small();
  const auto back = LamConfig::from_json(c.to_json());
  EXPECT_EQ(back.to_json(), c.to_json());
  auto bad = c.to_json();
  bad["num_heads"] = 3;
  EXPECT_NE(test::error_message([&] { LamConfig::from_json(bad); }).find("num_heads"), std::string::npos);
  bad = c.to_json();
  bad["model_dim"] = "wide";
  EXPECT_NE(test::error_message([&] { LamConfig::from_json(bad); }).find("model_dim"), std::string::npos);
}

TEST(Lam, GoldenParityBatch1And3) {
  auto g = open_golden();
  ASSERT_TRUE(g) << "golden fixture missing from " << test::golden_dir();
  auto model = golden_model(*g);
  torch::NoGradGuard no_grad;
  for (const std::string b : {"b1_", "b3_"}) {
    const auto out = model->forward(g->io.tensor(b + "videos"));
    EXPECT_LE(test::max_abs(out.z_mu, g->io.tensor(b + "mu")), 2e-5) << b;
    EXPECT_LE(test::max_abs(out.z_logvar, g->io.tensor(b + "logvar")), 2e-5) << b;
    EXPECT_LE(test::max_abs(out.z_rep, g->io.tensor(b + "z_rep")), 2e-5) << b;
    EXPECT_LE(test::max_abs(out.recon, g->io.tensor(b + "recon")), 1e-5) << b;
  }
}

TEST(Lam, GoldenWorldModelLatentActionsPerSample) {
  auto g = open_golden();
  ASSERT_TRUE(g) << "golden fixture missing from " << test::golden_dir();
  auto model = golden_model(*g);
  torch::NoGradGuard no_grad;
  const auto video = g->io.tensor("wm_lam_video");  // [3, 4, H, W, 3]: 2 pairs per sample
  const auto correct = lam_latent_actions(model, video);
  EXPECT_LE(test::max_abs(correct, g->io.tensor("wm_latent_action_correct")), 2e-5);
  const auto published = lam_latent_actions(model, video, /*published_order=*/true);
  EXPECT_LE(test::max_abs(published, g->io.tensor("wm_latent_action_published")), 2e-5);
  // The two orders really differ for B > 1, so the test above tells them apart.
  EXPECT_GT(test::max_abs(correct, published), 1e-3);
  // Injection into the action vector's last 32 dims.
  auto action = g->io.tensor("wm_action_in", true);
  action.slice(2, action.size(2) - 32).mul_(correct);
  EXPECT_LE(test::max_abs(action, g->io.tensor("wm_action_out_correct")), 2e-5);
  // Each sample's latent actions equal those of that sample encoded alone.
  for (int64_t b = 0; b < video.size(0); ++b) {
    const auto alone = lam_latent_actions(model, video.slice(0, b, b + 1));
    EXPECT_LE(test::max_abs(alone[0], correct[b]), 1e-5) << "sample " << b;
  }
}

TEST(Lam, SampleOutputDoesNotDependOnBatchMates) {
  torch::manual_seed(3);
  auto config = LamConfig::tiny();
  LatentActionModel model(config);
  model->eval();
  torch::NoGradGuard no_grad;
  const auto videos = torch::rand({4, 3, 48, 64, 3});  // T = 3: two transitions per sample
  const auto full = model->forward(videos);
  // Alone.
  const auto alone = model->forward(videos.slice(0, 2, 3));
  EXPECT_LE(test::max_abs(alone.z_mu, full.z_mu.slice(0, 4, 6)), 1e-5);
  EXPECT_LE(test::max_abs(alone.recon[0], full.recon[2]), 1e-5);
  // Batch reversed and batch mates replaced: sample 2's rows are unchanged.
  auto other = videos.flip({0}).clone();
  other[0] = torch::rand({3, 48, 64, 3});
  const auto rev = model->forward(other);  // original sample 2 sits at index 1
  EXPECT_LE(test::max_abs(rev.z_mu.slice(0, 2, 4), full.z_mu.slice(0, 4, 6)), 1e-5);
  EXPECT_LE(test::max_abs(rev.recon[1], full.recon[2]), 1e-5);
  // Changing one sample's second frame changes its own latent.
  auto changed = videos.clone();
  changed[2][1] = torch::rand({48, 64, 3});
  const auto ch = model->encode(changed);
  EXPECT_GT(test::max_abs(ch.z_mu.slice(0, 4, 5), full.z_mu.slice(0, 4, 5)), 1e-6);
  EXPECT_LE(test::max_abs(ch.z_mu.slice(0, 0, 4), full.z_mu.slice(0, 0, 4)), 1e-6);
}

TEST(Lam, PatchifyRoundTripAndLayout) {
  const auto v = torch::rand({2, 2, 32, 48, 3});
  const auto p = lam_patchify(v, 16);
  ASSERT_EQ(p.sizes(), (std::vector<int64_t>{2, 2, 6, 768}));
  // Patch (row 1, col 2), element (hp 3, wp 5, c 1) packs as (hp wp c).
  EXPECT_EQ(p[1][0][1 * 3 + 2][(3 * 16 + 5) * 3 + 1].item<float>(), v[1][0][16 + 3][32 + 5][1].item<float>());
  EXPECT_TRUE(torch::equal(lam_unpatchify(p, 16, 32, 48), v));
  // Sizes that are not multiples of the patch are cropped.
  EXPECT_EQ(lam_patchify(torch::rand({1, 2, 35, 50, 3}), 16).size(2), 6);
}

TEST(Lam, RotaryMatchesInterleavedFormula) {
  LamRotary rot(8);
  torch::manual_seed(0);                   // fixed inputs: the 1e-6 bound below is for values of this size
  const auto x = torch::randn({3, 2, 8});  // [N, T = 2, D]
  const auto y = rot->rotate(x);
  for (int64_t t = 0; t < 2; ++t)
    for (int64_t j = 0; j < 4; ++j) {
      const double f = std::pow(10000.0, -2.0 * j / 8), a = t * f;
      const auto x0 = x.select(1, t).select(1, 2 * j), x1 = x.select(1, t).select(1, 2 * j + 1);
      EXPECT_LE(test::max_abs(y.select(1, t).select(1, 2 * j), x0 * std::cos(a) - x1 * std::sin(a)), 1e-6);
      EXPECT_LE(test::max_abs(y.select(1, t).select(1, 2 * j + 1), x1 * std::cos(a) + x0 * std::sin(a)),
                1e-6);
    }
  // Position 0 is the identity.
  EXPECT_TRUE(torch::allclose(y.select(1, 0), x.select(1, 0)));
}

TEST(Lam, ReleasedSizeKeysAndShapesMatchReference) {
  const auto path = test::golden_dir() / "keys" / "lam_keys.tsv";
  ASSERT_TRUE(std::filesystem::exists(path)) << path << " is missing";
  std::vector<std::pair<std::string, std::string>> expected;
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty()) continue;
    const auto tab = line.find('\t');
    ASSERT_NE(tab, std::string::npos) << line;
    expected.emplace_back(line.substr(0, tab), line.substr(tab + 1));
  }
  ASSERT_EQ(expected.size(), 839u);
  torch::NoGradGuard no_grad;
  LatentActionModel model(LamConfig::released());
  const auto sd = state_dict(*model);
  std::vector<std::pair<std::string, std::string>> actual;
  int64_t numel = 0;
  for (const auto& [name, t] : sd) {
    actual.emplace_back("lam." + name, shape_string(t.sizes()));
    numel += t.numel();
  }
  EXPECT_EQ(actual, expected);  // same names, shapes and order
  EXPECT_NEAR(numel / 1e6, 709.8, 0.1);
}

TEST(Lam, ForwardFlopsCountsTheDominantMatmuls) {
  // Released size: 710M params, most of them applied to ~600 encoder and 300 decoder tokens per
  // pair, so ~2 * params * tokens as a rough lower bound on the count.
  const auto c = LamConfig::released();
  const double f = lam_forward_flops(c);
  EXPECT_GT(f, 2.0 * 405e6 * 602 * 0.9);
  EXPECT_LT(f, 2.0 * 710e6 * 602 * 1.5);
  // Doubling the width roughly quadruples the projection work.
  auto wide = LamConfig::tiny();
  wide.model_dim *= 2;
  EXPECT_GT(lam_forward_flops(wide), 2.5 * lam_forward_flops(LamConfig::tiny()));
}

}  // namespace dojo::models
