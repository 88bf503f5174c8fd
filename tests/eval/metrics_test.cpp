#include "eval/metrics.h"

#include <torch/torch.h>

#include <fstream>

#include <cmath>
#include <nlohmann/json.hpp>
#include <optional>
#include <regex>

#include "core/error.h"
#include "core/safetensors.h"
#include "core/state_dict.h"
#include "eval/lpips.h"
#include "io/video.h"
#include "test_util.h"

namespace dojo::eval {

namespace {

// A missing fixture fails the test that asks for it, naming the file: golden tests never skip
// (tests/golden/README.md).
std::optional<SafetensorsFile> open_images() {
  const auto path = test::golden_dir() / "metrics_images.safetensors";
  if (!std::filesystem::exists(path)) {
    ADD_FAILURE() << path << " is missing: golden fixtures are never skipped (tests/golden/README.md)";
    return std::nullopt;
  }
  return SafetensorsFile::open(path);
}

// The fixture stores uint8 [N, C, H, W]; the reader layout is [N, H, W, 3].
torch::Tensor nhwc(const torch::Tensor& nchw) { return nchw.permute({0, 2, 3, 1}).contiguous(); }

LpipsVgg random_lpips(uint64_t seed) {
  torch::manual_seed(seed);
  LpipsVgg net;
  torch::NoGradGuard no_grad;
  // Heads are non-negative in trained weights; keep that property.
  for (auto& head : net->heads) head->model[1]->as<torch::nn::Conv2d>()->weight.uniform_(0.0, 1.0);
  return net;
}

}  // namespace

TEST(Metrics, PsnrSsimMatchFixture) {
  auto f = open_images();
  ASSERT_TRUE(f) << "golden fixture missing from " << test::golden_dir();
  for (const std::string set : {"s64", "b480x640"}) {
    const auto x = f->tensor(set + "_x_u8");
    const auto y = f->tensor(set + "_y_u8");
    EXPECT_EQ(ssim_downsample_factor(x.size(2), x.size(3)),
              f->tensor(set + "_downsample_f")[0].item<int64_t>());
    // uint8 [N, H, W, 3] path and float [N, 3, H, W] path agree.
    const auto psnr = psnr_per_frame(nhwc(x), nhwc(y));
    const auto ssim = ssim_per_frame(nhwc(x), nhwc(y));
    const auto psnr_f = psnr_per_frame(x.to(torch::kFloat) / 255.0, y.to(torch::kFloat) / 255.0);
    const auto ssim_f = ssim_per_frame(x.to(torch::kFloat) / 255.0, y.to(torch::kFloat) / 255.0);
    const double psnr_err = test::max_abs(psnr, f->tensor(set + "_psnr_per_image"));
    const double ssim_err = test::max_abs(ssim, f->tensor(set + "_ssim_per_image"));
    EXPECT_LE(psnr_err, 1e-4) << set;
    EXPECT_LE(ssim_err, 2e-5) << set;
    EXPECT_LE(test::max_abs(psnr_f, psnr), 1e-5) << set;
    EXPECT_LE(test::max_abs(ssim_f, ssim), 1e-6) << set;
    // Per-video value = mean of per-frame values (what the eval logs).
    const auto video = video_metrics(nhwc(x), nhwc(y), nullptr, 3);
    EXPECT_EQ(video.num_frames, x.size(0));
    EXPECT_NEAR(video.psnr, f->tensor(set + "_psnr_mean")[0].item<double>(), 1e-4) << set;
    EXPECT_NEAR(video.ssim, f->tensor(set + "_ssim_mean")[0].item<double>(), 2e-5) << set;
    EXPECT_TRUE(std::isnan(video.lpips));
    std::cout << set << " parity max abs: psnr " << psnr_err << " dB, ssim " << ssim_err << "\n";
  }
}

TEST(Metrics, IdenticalFramesAndDownsampleRule) {
  const auto a = torch::rand({2, 3, 40, 48});
  EXPECT_TRUE(torch::allclose(psnr_per_frame(a, a), torch::full({2}, 80.0f)));
  EXPECT_TRUE(torch::allclose(ssim_per_frame(a, a), torch::ones({2})));
  EXPECT_EQ(ssim_downsample_factor(480, 640), 2);  // round(1.875)
  EXPECT_EQ(ssim_downsample_factor(240, 320), 1);  // round(0.9375)
  EXPECT_EQ(ssim_downsample_factor(384, 400), 2);  // round(1.5) = 2 (half to even)
  EXPECT_EQ(ssim_downsample_factor(640, 700), 2);  // round(2.5) = 2 (half to even)
  EXPECT_EQ(ssim_downsample_factor(896, 900), 4);  // round(3.5) = 4
  EXPECT_EQ(ssim_downsample_factor(100, 900), 1);
  // Hand value: constant frames differing by 0.1 everywhere -> mse 0.01 -> 20 dB.
  EXPECT_NEAR(
      psnr_per_frame(torch::full({1, 3, 16, 16}, 0.5), torch::full({1, 3, 16, 16}, 0.6))[0].item<double>(),
      -10 * std::log10(0.01 + 1e-8), 1e-4);
  EXPECT_THROW(ssim_per_frame(torch::rand({1, 3, 8, 8}), torch::rand({1, 3, 8, 8})), Error);
  EXPECT_THROW(psnr_per_frame(a, a.narrow(3, 0, 40)), Error);
  EXPECT_THROW(
      psnr_per_frame(torch::zeros({1, 8, 8, 3}, torch::kInt), torch::zeros({1, 8, 8, 3}, torch::kInt)),
      Error);
}

TEST(Metrics, DatasetMeanWeighsVideosEqually) {
  VideoMetrics a, b;
  a.psnr = 30, a.ssim = 0.9, a.num_frames = 49;
  b.psnr = 20, b.ssim = 0.5, b.num_frames = 10;
  const auto m = dataset_mean({a, b});
  EXPECT_DOUBLE_EQ(m.psnr, 25);
  EXPECT_DOUBLE_EQ(m.ssim, 0.7);
  EXPECT_EQ(m.num_frames, 59);
  EXPECT_TRUE(std::isnan(m.lpips));
  EXPECT_THROW(dataset_mean({}), Error);
}

TEST(Metrics, PearsonAndMmrvMatchFixture) {
  const auto path = test::golden_dir() / "metrics_values.json";
  ASSERT_TRUE(std::filesystem::exists(path)) << path << " is missing";
  const auto j = nlohmann::json::parse(test::read_file(path));
  const auto& cases = j.at("simpler_rank_metrics");
  ASSERT_GE(cases.size(), 8u);
  for (const auto& c : cases) {
    const auto sim = c.at("perf_sim").get<std::vector<double>>();
    const auto real = c.at("perf_real").get<std::vector<double>>();
    EXPECT_NEAR(mean_maximum_rank_violation(sim, real), c.at("mmrv").get<double>(), 1e-12) << c.dump();
    EXPECT_NEAR(pearson_correlation(sim, real), c.at("pearson").get<double>(), 1e-12) << c.dump();
  }
  // The piq numbers repeated in the JSON agree with the safetensors fixture.
  auto f = open_images();
  ASSERT_TRUE(f) << "golden fixture missing from " << test::golden_dir();
  const auto means = j.at("piq").at("b480x640").at("ssim_mean").get<std::vector<double>>();
  EXPECT_NEAR(means.at(0), f->tensor("b480x640_ssim_mean")[0].item<double>(), 1e-7);
}

TEST(Metrics, PearsonAndMmrvHandExamples) {
  // metrics.md §6 test vectors from SimplerEnv's own tables.
  const std::vector<double> coke_sim = {0.787, 0.857, 0.710, 0.567, 0.027, 0.170};
  const std::vector<double> coke_real = {0.907, 0.853, 0.920, 0.760, 0.133, 0.293};
  EXPECT_NEAR(mean_maximum_rank_violation(coke_sim, coke_real), 0.031333, 1e-6);
  EXPECT_NEAR(mean_maximum_rank_violation(coke_real, coke_sim), 0.061833, 1e-6);
  EXPECT_NEAR(pearson_correlation(coke_sim, coke_real), 0.975434, 1e-6);
  const std::vector<double> carrot_sim = {0.042, 0.083, 0.097};
  const std::vector<double> carrot_real = {0.000, 0.250, 0.083};
  EXPECT_NEAR(mean_maximum_rank_violation(carrot_sim, carrot_real), 0.111333, 1e-6);
  EXPECT_NEAR(mean_maximum_rank_violation(carrot_real, carrot_sim), 0.009333, 1e-6);
  EXPECT_NEAR(pearson_correlation(carrot_sim, carrot_real), 0.571368, 1e-6);
  // By hand: one swapped pair (0.2, 0.4) in real -> rows 1 and 2 violate by 0.2 -> MMRV 0.4/3.
  EXPECT_NEAR(mean_maximum_rank_violation({0.1, 0.2, 0.3}, {0.1, 0.4, 0.2}), 0.4 / 3, 1e-15);
  // Perfectly anti-correlated with a long vector (pairwise-sum path of more than 8 values).
  std::vector<double> up, down;
  for (int i = 0; i < 20; ++i) {
    up.push_back(0.05 * i);
    down.push_back(1.0 - 0.05 * i);
  }
  EXPECT_NEAR(pearson_correlation(up, down), -1.0, 1e-7);
  EXPECT_THROW(pearson_correlation({0.1}, {0.1, 0.2}), Error);
  EXPECT_THROW(mean_maximum_rank_violation({}, {}), Error);
}

TEST(Metrics, LpipsWithoutWeightsSaysWhatIsMissing) {
  const Lpips none;
  EXPECT_FALSE(none.available());
  const auto frames = torch::zeros({1, 16, 16, 3}, torch::kByte);
  const auto msg = test::error_message([&] { none.per_frame(frames, frames); });
  EXPECT_NE(msg.find("--lpips-weights"), std::string::npos) << msg;
  EXPECT_NE(msg.find("docs/evaluation.md"), std::string::npos) << msg;
  const auto missing = test::error_message([] { Lpips::load({"/nonexistent/lpips_vgg.safetensors"}); });
  EXPECT_NE(missing.find("/nonexistent/lpips_vgg.safetensors"), std::string::npos) << missing;
  EXPECT_NE(test::error_message([] { Lpips::load({}); }).find("--lpips-weights"), std::string::npos);
}

TEST(Metrics, LpipsRandomNetProperties) {
  const auto metric = Lpips::from_network(random_lpips(0));
  torch::manual_seed(5);
  const auto x = torch::rand({2, 3, 32, 32});
  const auto y = (x + 0.2 * torch::randn_like(x)).clamp(0, 1);
  const auto d = metric.per_frame(x, y);
  ASSERT_EQ(d.sizes(), torch::IntArrayRef({2}));
  EXPECT_GT(d.min().item<double>(), 0.0);
  EXPECT_LE(test::max_abs(metric.per_frame(y, x), d), 1e-5);           // symmetric
  EXPECT_LE(metric.per_frame(x, x).abs().max().item<double>(), 1e-7);  // identical -> 0
  // Larger perturbations are further away.
  const auto far = (x + 0.5 * torch::randn_like(x)).clamp(0, 1);
  EXPECT_GT(metric.per_frame(x, far).mean().item<double>(), d.mean().item<double>());
  // video_metrics fills lpips with the per-frame mean.
  const auto v = video_metrics(x, y, &metric, 1);
  EXPECT_NEAR(v.lpips, d.mean().item<double>(), 1e-6);
}

TEST(Metrics, LpipsFirstTapByHand) {
  // Only head 0 non-zero (all ones): LPIPS = mean over positions of Σ_c (unit(f_x) − unit(f_y))²,
  // f = relu(conv2(relu(conv0(normalised input)))).
  auto net = random_lpips(1);
  {
    torch::NoGradGuard no_grad;
    for (size_t k = 0; k < net->heads.size(); ++k)
      net->heads[k]->model[1]->as<torch::nn::Conv2d>()->weight.fill_(k == 0 ? 1.0 : 0.0);
  }
  const auto metric = Lpips::from_network(net);
  torch::manual_seed(2);
  const auto x = torch::rand({1, 3, 20, 20});
  const auto y = torch::rand({1, 3, 20, 20});
  const auto conv0 = net->features[0]->as<torch::nn::Conv2d>();
  const auto conv2 = net->features[2]->as<torch::nn::Conv2d>();
  const auto feat = [&](const torch::Tensor& img) {
    torch::NoGradGuard no_grad;
    const auto mean = torch::tensor({0.485, 0.456, 0.406}).view({1, 3, 1, 1});
    const auto std = torch::tensor({0.229, 0.224, 0.225}).view({1, 3, 1, 1});
    auto f = torch::relu(conv2->forward(torch::relu(conv0->forward((img - mean) / std))));
    return f / (f.pow(2).sum(1, true).sqrt() + 1e-10);
  };
  const double expected = (feat(x) - feat(y)).pow(2).sum(1).mean().item<double>();
  EXPECT_NEAR(metric.per_frame(x, y)[0].item<double>(), expected, 1e-5);
}

TEST(Metrics, LpipsLoaderAcceptsTorchvisionAndOfficialNames) {
  test::TempDir dir;
  auto net = random_lpips(3);
  const auto reference = Lpips::from_network(net);
  torch::manual_seed(4);
  const auto x = torch::randint(0, 256, {1, 24, 24, 3}, torch::kByte);
  const auto y = torch::randint(0, 256, {1, 24, 24, 3}, torch::kByte);
  const auto expected = reference.per_frame(x, y);

  // One file with torchvision / official-head names.
  save_safetensors(dir / "all.safetensors", state_dict(*net));
  EXPECT_LE(test::max_abs(Lpips::load({dir / "all.safetensors"}).per_frame(x, y), expected), 1e-6);

  // Official lpips model names (net.slice<k>.<i>.*, lin<k>.weight) split over two files, plus a
  // VGG classifier tensor that is ignored.
  NamedTensors trunk, heads;
  const std::vector<int> slice_end = {4, 9, 16, 23, 30};
  for (const auto& [name, t] : state_dict(*net)) {
    std::smatch m;
    static const std::regex feat(R"(^features\.(\d+)\.(.*)$)");
    if (std::regex_match(name, m, feat)) {
      const int i = std::stoi(m[1]);
      int k = 0;
      while (i >= slice_end[k]) ++k;
      trunk.emplace_back("net.slice" + std::to_string(k + 1) + "." + m[1].str() + "." + m[2].str(), t);
    } else {
      heads.emplace_back(name.substr(0, 4) + ".weight", t);  // "lin3.model.1.weight" -> "lin3.weight"
    }
  }
  trunk.emplace_back("classifier.0.weight", torch::zeros({2, 2}));
  save_safetensors(dir / "trunk.safetensors", trunk);
  save_safetensors(dir / "heads.safetensors", heads);
  EXPECT_LE(test::max_abs(Lpips::load({dir / "trunk.safetensors", dir / "heads.safetensors"}).per_frame(x, y),
                          expected),
            1e-6);

  // Heads forgotten: the error names them.
  const auto msg = test::error_message([&] { Lpips::load({dir / "trunk.safetensors"}); });
  EXPECT_NE(msg.find("lin0.model.1.weight"), std::string::npos) << msg;
  EXPECT_NE(msg.find("trunk.safetensors"), std::string::npos) << msg;
  // A stray tensor is reported as unexpected.
  heads.emplace_back("something.else", torch::zeros({1}));
  save_safetensors(dir / "heads2.safetensors", heads);
  const auto stray = test::error_message([&] {
    Lpips::load({dir / "trunk.safetensors", dir / "heads2.safetensors"});
  });
  EXPECT_NE(stray.find("something.else"), std::string::npos) << stray;
}

TEST(Metrics, CliComparesTwoVideos) {
  test::TempDir dir;
  // A smooth moving pattern (compresses well) and a noisier copy.
  const auto ramp = torch::linspace(0, 1, 64);
  std::vector<torch::Tensor> frames;
  for (int t = 0; t < 4; ++t) {
    const auto img = torch::sin(6.0 * (ramp.view({64, 1}) + ramp.view({1, 64})) + 0.3 * t);  // [64, 64]
    frames.push_back(((img * 0.4 + 0.5) * 255).to(torch::kByte).unsqueeze(-1).expand({64, 64, 3}));
  }
  const auto video = torch::stack(frames);  // [4, 64, 64, 3]
  torch::manual_seed(6);
  const auto noisy =
      (video.to(torch::kFloat) + 20 * torch::randn(video.sizes())).clamp(0, 255).to(torch::kByte);
  io::write_video((dir / "a.mp4").string(), video);
  io::write_video((dir / "b.mp4").string(), noisy);

  const auto same = test::run_dojo("metrics video " + (dir / "a.mp4").string() + " " +
                                   (dir / "a.mp4").string() + " --json");
  ASSERT_EQ(same.exit_code, 0) << same.output;
  const auto j = nlohmann::json::parse(same.output);
  EXPECT_EQ(j.at("frames").get<int>(), 4);
  EXPECT_NEAR(j.at("psnr").get<double>(), 80.0, 1e-3);
  EXPECT_NEAR(j.at("ssim").get<double>(), 1.0, 1e-6);
  EXPECT_TRUE(j.at("lpips").is_null());

  const auto diff = test::run_dojo("metrics video " + (dir / "a.mp4").string() + " " +
                                   (dir / "b.mp4").string() + " --json");
  ASSERT_EQ(diff.exit_code, 0) << diff.output;
  const auto d = nlohmann::json::parse(diff.output);
  EXPECT_LT(d.at("psnr").get<double>(), 40.0);
  EXPECT_GT(d.at("psnr").get<double>(), 10.0);
  EXPECT_LT(d.at("ssim").get<double>(), 0.99);

  const auto missing =
      test::run_dojo("metrics video " + (dir / "a.mp4").string() + " " + (dir / "b.mp4").string() +
                     " --lpips-weights " + (dir / "none.safetensors").string());
  EXPECT_EQ(missing.exit_code, 1);
  EXPECT_NE(missing.output.find("none.safetensors"), std::string::npos) << missing.output;
}

TEST(Metrics, SpearmanUsesAverageRanks) {
  EXPECT_DOUBLE_EQ(spearman_correlation({0.1, 0.5, 0.9}, {0.2, 0.3, 0.4}), 1.0);
  EXPECT_NEAR(spearman_correlation({0.1, 0.5, 0.9}, {0.4, 0.3, 0.2}), -1.0, 1e-8);
  // Ties share their mean rank: ranks (1.5, 1.5, 3) against (1, 2, 3).
  const double r = spearman_correlation({0.2, 0.2, 0.9}, {0.1, 0.2, 0.3});
  EXPECT_NEAR(r, pearson_correlation({1.5, 1.5, 3}, {1, 2, 3}), 1e-12);
  EXPECT_LT(r, 1.0);
}

TEST(Metrics, CliRanksPoliciesFromJson) {
  test::TempDir dir;
  std::ofstream(dir / "rates.json") << R"({"policies": [{"name": "expert", "world_model": 0.9, "real": 0.8},
                          {"name": "medium", "world_model": 0.6, "real": 0.5},
                          {"name": "poor", "world_model": 0.1, "real": 0.2}]})";
  const auto r = test::run_dojo("metrics policies " + (dir / "rates.json").string() + " --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto j = nlohmann::json::parse(r.output);
  const std::vector<double> wm = {0.9, 0.6, 0.1}, real = {0.8, 0.5, 0.2};
  EXPECT_DOUBLE_EQ(j.at("pearson_r").get<double>(), pearson_correlation(wm, real));
  EXPECT_DOUBLE_EQ(j.at("mmrv").get<double>(), 0.0);  // the ranking is right
  EXPECT_DOUBLE_EQ(j.at("spearman_rho").get<double>(), 1.0);
  EXPECT_NEAR(j.at("mean_abs_gap").get<double>(), 0.1, 1e-12);
  EXPECT_EQ(j.at("policies").get<int>(), 3);

  std::ofstream(dir / "bad.json") << R"({"policies": [{"name": "a", "world_model": 1.5, "real": 0.1},
                                                     {"name": "b", "world_model": 0.5, "real": 0.1}]})";
  const auto bad = test::run_dojo("metrics policies " + (dir / "bad.json").string());
  EXPECT_EQ(bad.exit_code, 1);
  EXPECT_NE(bad.output.find("policies[0].world_model"), std::string::npos) << bad.output;
  EXPECT_NE(bad.output.find("bad.json"), std::string::npos) << bad.output;
}

}  // namespace dojo::eval
