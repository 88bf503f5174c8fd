#include "eval/metrics.h"

#include <algorithm>
#include <cmath>
#include <string>

#include <nlohmann/json.hpp>

#include "core/error.h"
#include "core/json_file.h"
#include "eval/lpips.h"

namespace dojo::eval {

namespace {

void check_pair(const torch::Tensor& pred, const torch::Tensor& gt, const char* what) {
  DOJO_CHECK(pred.sizes() == gt.sizes(), std::string(what) + ": prediction " + c10::str(pred.sizes()) +
                                             " and ground truth " + c10::str(gt.sizes()) +
                                             " differ in shape");
}

// piq's gaussian_filter(11, 1.5): float32 coords i − 5, exp(−(dx² + dy²)/(2σ²)), normalised.
torch::Tensor ssim_kernel(int64_t channels, const torch::TensorOptions& options) {
  const int64_t size = 11;
  const double sigma = 1.5;
  auto coords = torch::arange(size, torch::kFloat) - (size - 1) / 2.0;  // [11]
  auto g = coords.pow(2);
  auto kernel = (-(g.unsqueeze(0) + g.unsqueeze(1)) / (2 * sigma * sigma)).exp();  // [11, 11]
  kernel = kernel / kernel.sum();
  return kernel.view({1, 1, size, size}).repeat({channels, 1, 1, 1}).to(options);  // [C, 1, 11, 11]
}

// numpy's float64 np.add.reduce of a contiguous vector: the first element is the initial value,
// the rest is summed pairwise (blocks of 8 partial sums below 128 elements, halving above).
double numpy_pairwise(const double* a, size_t n) {
  if (n < 8) {
    double res = 0.0;
    for (size_t i = 0; i < n; ++i) res += a[i];
    return res;
  }
  if (n <= 128) {
    double r[8];
    for (int j = 0; j < 8; ++j) r[j] = a[j];
    size_t i = 8;
    for (; i < n - (n % 8); i += 8)
      for (int j = 0; j < 8; ++j) r[j] += a[i + j];
    double res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
    for (; i < n; ++i) res += a[i];
    return res;
  }
  size_t n2 = n / 2;
  n2 -= n2 % 8;
  return numpy_pairwise(a, n2) + numpy_pairwise(a + n2, n - n2);
}

double numpy_sum(const std::vector<double>& v) {
  if (v.empty()) return 0.0;
  return v[0] + numpy_pairwise(v.data() + 1, v.size() - 1);
}

double numpy_mean(const std::vector<double>& v) { return numpy_sum(v) / static_cast<double>(v.size()); }

void check_rates(const std::vector<double>& sim, const std::vector<double>& real, const char* what) {
  DOJO_CHECK(!sim.empty(), std::string(what) + ": no values");
  DOJO_CHECK(sim.size() == real.size(), std::string(what) + ": " + std::to_string(sim.size()) +
                                            " world-model values but " + std::to_string(real.size()) +
                                            " real-world values");
}

}  // namespace

torch::Tensor to_unit_frames(const torch::Tensor& frames) {
  if (frames.scalar_type() == torch::kByte) {
    DOJO_CHECK(frames.dim() == 4 && frames.size(3) == 3,
               "metrics: uint8 frames must be [N, H, W, 3], got " + c10::str(frames.sizes()));
    return frames.permute({0, 3, 1, 2}).to(torch::kFloat).div(255.0).clamp(0.0, 1.0);  // [N, 3, H, W]
  }
  DOJO_CHECK(at::isFloatingType(frames.scalar_type()),
             "metrics: frames must be uint8 [N, H, W, 3] or float [N, 3, H, W]");
  DOJO_CHECK(frames.dim() == 4 && frames.size(1) == 3,
             "metrics: float frames must be [N, 3, H, W], got " + c10::str(frames.sizes()));
  return frames.to(torch::kFloat).clamp(0.0, 1.0);
}

torch::Tensor psnr_per_frame(const torch::Tensor& pred, const torch::Tensor& gt) {
  check_pair(pred, gt, "psnr");
  const auto x = to_unit_frames(pred);
  const auto y = to_unit_frames(gt);
  const auto mse = (x - y).pow(2).mean({1, 2, 3});  // [N]
  return -10.0 * torch::log10(mse + 1e-8);
}

int64_t ssim_downsample_factor(int64_t height, int64_t width) {
  // Python's round() rounds halves to even; nearbyint does too under the default rounding mode.
  const double ratio = static_cast<double>(std::min(height, width)) / 256.0;
  return std::max<int64_t>(1, static_cast<int64_t>(std::nearbyint(ratio)));
}

torch::Tensor ssim_per_frame(const torch::Tensor& pred, const torch::Tensor& gt) {
  check_pair(pred, gt, "ssim");
  auto x = to_unit_frames(pred);  // [N, 3, H, W]
  auto y = to_unit_frames(gt);
  const int64_t f = ssim_downsample_factor(x.size(2), x.size(3));
  if (f > 1) {
    x = torch::avg_pool2d(x, {f, f});  // [N, 3, H/f, W/f]
    y = torch::avg_pool2d(y, {f, f});
  }
  DOJO_CHECK(x.size(2) >= 11 && x.size(3) >= 11,
             "ssim: frames must be at least 11 x 11 after downsampling, got " + std::to_string(x.size(2)) +
                 " x " + std::to_string(x.size(3)));
  const int64_t channels = x.size(1);
  const auto kernel = ssim_kernel(channels, x.options());
  const std::vector<int64_t> ones = {1, 1}, zeros = {0, 0};
  const auto blur = [&](const torch::Tensor& t) {
    return torch::conv2d(t, kernel, torch::Tensor(), ones, zeros, ones,
                         channels);  // valid: [N, C, H − 10, W − 10]
  };
  const double c1 = 0.01 * 0.01;
  const double c2 = 0.03 * 0.03;
  const auto mu_x = blur(x);
  const auto mu_y = blur(y);
  const auto mu_xx = mu_x.pow(2);
  const auto mu_yy = mu_y.pow(2);
  const auto mu_xy = mu_x * mu_y;
  const auto sigma_xx = blur(x.pow(2)) - mu_xx;
  const auto sigma_yy = blur(y.pow(2)) - mu_yy;
  const auto sigma_xy = blur(x * y) - mu_xy;
  const auto cs = (2.0 * sigma_xy + c2) / (sigma_xx + sigma_yy + c2);
  const auto ssim_map = (2.0 * mu_xy + c1) / (mu_xx + mu_yy + c1) * cs;  // [N, C, h, w]
  return ssim_map.mean({-1, -2}).mean(1);                                // [N]
}

VideoMetrics video_metrics(const torch::Tensor& pred, const torch::Tensor& gt, const Lpips* lpips,
                           int64_t chunk) {
  check_pair(pred, gt, "video_metrics");
  DOJO_CHECK(pred.dim() == 4 && pred.size(0) > 0, "video_metrics: need a non-empty [N, ...] frame batch");
  DOJO_CHECK(chunk >= 1, "video_metrics: chunk must be >= 1");
  const int64_t n = pred.size(0);
  double psnr_sum = 0, ssim_sum = 0, lpips_sum = 0;
  for (int64_t start = 0; start < n; start += chunk) {
    const int64_t len = std::min(chunk, n - start);
    const auto p = pred.narrow(0, start, len);
    const auto g = gt.narrow(0, start, len);
    psnr_sum += psnr_per_frame(p, g).to(torch::kDouble).sum().item<double>();
    ssim_sum += ssim_per_frame(p, g).to(torch::kDouble).sum().item<double>();
    if (lpips) lpips_sum += lpips->per_frame(p, g).to(torch::kDouble).sum().item<double>();
  }
  VideoMetrics out;
  out.num_frames = n;
  out.psnr = psnr_sum / n;
  out.ssim = ssim_sum / n;
  if (lpips) out.lpips = lpips_sum / n;
  return out;
}

VideoMetrics dataset_mean(const std::vector<VideoMetrics>& videos) {
  DOJO_CHECK(!videos.empty(), "dataset_mean: no videos");
  VideoMetrics out;
  out.psnr = out.ssim = out.lpips = 0;
  for (const auto& v : videos) {
    out.psnr += v.psnr;
    out.ssim += v.ssim;
    out.lpips += v.lpips;  // NaN propagates
    out.num_frames += v.num_frames;
  }
  const double count = static_cast<double>(videos.size());
  out.psnr /= count;
  out.ssim /= count;
  out.lpips /= count;
  return out;
}

double pearson_correlation(const std::vector<double>& sim, const std::vector<double>& real) {
  check_rates(sim, real, "pearson_correlation");
  const size_t n = sim.size();
  const double mean_s = numpy_mean(sim);
  const double mean_r = numpy_mean(real);
  std::vector<double> s(n), r(n);
  bool equal = true;
  for (size_t i = 0; i < n; ++i) {
    s[i] = sim[i] - mean_s;
    r[i] = real[i] - mean_r;
    equal = equal && s[i] == r[i];
  }
  // Exact equality is the reference's special case (it also makes two constant vectors give 1).
  if (equal) return 1.0;
  std::vector<double> sr(n), ss(n), rr(n);
  for (size_t i = 0; i < n; ++i) {
    sr[i] = s[i] * r[i];
    ss[i] = s[i] * s[i];
    rr[i] = r[i] * r[i];
  }
  return numpy_sum(sr) / (std::sqrt(numpy_sum(ss) * numpy_sum(rr)) + 1e-8);
}

double mean_maximum_rank_violation(const std::vector<double>& sim, const std::vector<double>& real) {
  check_rates(sim, real, "mean_maximum_rank_violation");
  const size_t n = sim.size();
  std::vector<double> worst(n, 0.0);
  for (size_t i = 0; i < n; ++i)
    for (size_t j = 0; j < n; ++j)
      if ((sim[i] > sim[j]) != (real[i] > real[j]))
        worst[i] = std::max(worst[i], std::abs(real[i] - real[j]));
  return numpy_mean(worst);
}

namespace {

// Ranks 1..n with ties sharing the mean of the ranks they span.
std::vector<double> average_ranks(const std::vector<double>& v) {
  std::vector<size_t> order(v.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return v[a] < v[b]; });
  std::vector<double> ranks(v.size());
  for (size_t i = 0; i < order.size();) {
    size_t j = i;
    while (j + 1 < order.size() && v[order[j + 1]] == v[order[i]]) ++j;
    const double mean_rank = 0.5 * static_cast<double>(i + j) + 1.0;
    for (size_t k = i; k <= j; ++k) ranks[order[k]] = mean_rank;
    i = j + 1;
  }
  return ranks;
}

}  // namespace

double spearman_correlation(const std::vector<double>& sim, const std::vector<double>& real) {
  check_rates(sim, real, "spearman_correlation");
  return pearson_correlation(average_ranks(sim), average_ranks(real));
}

nlohmann::json PolicyAgreement::to_json() const {
  return {{"pearson_r", pearson}, {"mmrv", mmrv}, {"spearman_rho", spearman}, {"mean_abs_gap", mean_abs_gap}};
}

PolicyAgreement policy_agreement(const PolicyRates& rates) {
  PolicyAgreement a;
  a.pearson = pearson_correlation(rates.world_model, rates.real);
  a.mmrv = mean_maximum_rank_violation(rates.world_model, rates.real);
  a.spearman = spearman_correlation(rates.world_model, rates.real);
  std::vector<double> gaps;
  for (size_t i = 0; i < rates.real.size(); ++i)
    gaps.push_back(std::abs(rates.world_model[i] - rates.real[i]));
  a.mean_abs_gap = numpy_mean(gaps);
  return a;
}

PolicyRates read_policy_rates(const std::filesystem::path& path) {
  const auto j = read_json_file(path);
  const std::string where = path.string();
  DOJO_CHECK(j.is_object() && j.contains("policies") && j["policies"].is_array(),
             where + ": expected an object with an array 'policies'");
  PolicyRates r;
  for (size_t i = 0; i < j["policies"].size(); ++i) {
    const auto& p = j["policies"][i];
    const std::string field = where + ": policies[" + std::to_string(i) + "]";
    DOJO_CHECK(p.is_object(), field + " must be an object");
    auto rate = [&](const char* key) {
      DOJO_CHECK(p.contains(key) && p[key].is_number(), field + "." + key + " must be a number");
      const double v = p[key].get<double>();
      DOJO_CHECK(v >= 0 && v <= 1,
                 field + "." + key + " must be a success rate in [0, 1] (got " + std::to_string(v) + ")");
      return v;
    };
    r.names.push_back(p.contains("name") && p["name"].is_string() ? p["name"].get<std::string>()
                                                                  : "policy " + std::to_string(i));
    r.world_model.push_back(rate("world_model"));
    r.real.push_back(rate("real"));
  }
  DOJO_CHECK(r.real.size() >= 2, where + ": policies needs at least two entries to rank");
  return r;
}

}  // namespace dojo::eval
