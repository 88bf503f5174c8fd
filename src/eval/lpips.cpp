#include "eval/lpips.h"

#include <regex>

#include "core/error.h"
#include "core/safetensors.h"
#include "core/state_dict.h"
#include "eval/metrics.h"

namespace dojo::eval {

namespace {

// torchvision VGG16 "D" configuration up to relu5_3 (index 29): 0 = max-pool.
const std::vector<int64_t> kVggLayout = {64, 64,  0,   128, 128, 0,   256, 256, 256,
                                         0,  512, 512, 512, 0,   512, 512, 512};
// Indices in `features` after which LPIPS taps the activations (relu1_2 … relu5_3).
const std::vector<int64_t> kTaps = {3, 8, 15, 22, 29};
const std::vector<int64_t> kTapChannels = {64, 128, 256, 512, 512};

std::string join_paths(const std::vector<std::filesystem::path>& files) {
  std::string out;
  for (const auto& f : files) out += (out.empty() ? "" : ", ") + f.string();
  return out;
}

// Maps a file-side name to ours; "" for tensors that are not part of LPIPS (the VGG classifier).
std::string canonical_name(const std::string& name) {
  static const std::regex slice(R"(^net\.slice[1-5]\.(\d+)\.(weight|bias)$)");
  static const std::regex short_head(R"(^lin([0-4])\.weight$)");
  std::smatch m;
  if (std::regex_match(name, m, slice)) return "features." + m[1].str() + "." + m[2].str();
  if (std::regex_match(name, m, short_head)) return "lin" + m[1].str() + ".model.1.weight";
  if (name.rfind("classifier.", 0) == 0) return "";
  return name;
}

}  // namespace

LpipsHeadImpl::LpipsHeadImpl(int64_t channels) {
  model = register_module(
      "model",
      torch::nn::Sequential(torch::nn::Dropout(0.5),
                            torch::nn::Conv2d(torch::nn::Conv2dOptions(channels, 1, 1).bias(false))));
}

const torch::Tensor& LpipsHeadImpl::weight() const { return model->ptr(1)->as<torch::nn::Conv2d>()->weight; }

LpipsVggImpl::LpipsVggImpl() {
  torch::nn::Sequential seq;
  int64_t in = 3;
  for (int64_t width : kVggLayout) {
    if (width == 0) {
      seq->push_back(torch::nn::MaxPool2d(torch::nn::MaxPool2dOptions(2).stride(2)));
      continue;
    }
    seq->push_back(torch::nn::Conv2d(torch::nn::Conv2dOptions(in, width, 3).padding(1)));
    seq->push_back(torch::nn::ReLU());
    in = width;
  }
  features = register_module("features", seq);  // 30 modules, indices 0 … 29
  for (size_t k = 0; k < kTapChannels.size(); ++k)
    heads.push_back(register_module("lin" + std::to_string(k), LpipsHead(kTapChannels[k])));
}

torch::Tensor LpipsVggImpl::forward(const torch::Tensor& x, const torch::Tensor& y) {
  // ImageNet normalisation; equal to the official ScalingLayer applied to 2x − 1.
  const auto opts = x.options();
  const auto mean = torch::tensor({0.485, 0.456, 0.406}, opts).view({1, 3, 1, 1});
  const auto std = torch::tensor({0.229, 0.224, 0.225}, opts).view({1, 3, 1, 1});
  const int64_t n = x.size(0);
  // Both images go through the trunk as one batch.
  auto h = (torch::cat({x, y}) - mean) / std;  // [2N, 3, H, W]
  auto total = torch::zeros({n}, opts);
  size_t tap = 0;
  int64_t index = 0;
  for (auto& layer : *features) {
    if (tap == kTaps.size()) break;
    h = layer.forward(h);
    if (index++ != kTaps[tap]) continue;
    const auto unit = h / (h.pow(2).sum(1, true).sqrt() + 1e-10);            // [2N, C, h, w]
    const auto diff = (unit.narrow(0, 0, n) - unit.narrow(0, n, n)).pow(2);  // [N, C, h, w]
    const auto w = heads[tap]->weight().view({1, -1, 1, 1});                 // [1, C, 1, 1]
    total = total + (diff * w).mean({2, 3}).sum(1);                          // [N]
    ++tap;
  }
  return total;
}

void load_lpips_weights(LpipsVgg& net, const std::vector<std::filesystem::path>& files) {
  DOJO_CHECK(!files.empty(), lpips_missing_weights_message());
  NamedTensors tensors;
  for (const auto& path : files) {
    DOJO_CHECK(std::filesystem::exists(path), "LPIPS weights file not found: " + path.string() +
                                                  " (conversion from the official .pth: docs/evaluation.md)");
    const auto file = SafetensorsFile::open(path);
    for (const auto& name : file.keys()) {
      const auto ours = canonical_name(name);
      if (!ours.empty()) tensors.emplace_back(ours, file.tensor(name));
    }
  }
  LoadOptions options;
  options.strict = false;
  const auto report = load_state_dict(*net, tensors, options);
  DOJO_CHECK(report.ok(),
             "LPIPS weights (" + join_paths(files) + "): " + report.to_string("; ") +
                 " (expected VGG16 features.* and lin0..4.model.1.weight; see docs/evaluation.md)");
}

Lpips Lpips::load(const std::vector<std::filesystem::path>& files) {
  LpipsVgg net;
  load_lpips_weights(net, files);
  return from_network(net);
}

Lpips Lpips::from_network(LpipsVgg net) {
  net->eval();
  for (auto& p : net->parameters()) p.set_requires_grad(false);
  Lpips out;
  out.net_ = net;
  return out;
}

torch::Tensor Lpips::per_frame(const torch::Tensor& pred, const torch::Tensor& gt) const {
  DOJO_CHECK(available(), lpips_missing_weights_message());
  DOJO_CHECK(pred.sizes() == gt.sizes(), "lpips: prediction and ground truth differ in shape");
  torch::NoGradGuard no_grad;
  const auto param = net_->parameters().front();
  const auto x = to_unit_frames(pred).to(param.device(), param.scalar_type());
  const auto y = to_unit_frames(gt).to(param.device(), param.scalar_type());
  return net_->forward(x, y).to(torch::kCPU, torch::kFloat);
}

std::string lpips_missing_weights_message() {
  return "LPIPS needs weights: pass --lpips-weights FILE.safetensors (VGG16 features.* + "
         "lin0..4.model.1.weight, "
         "converted from torchvision vgg16 and lpips/weights/v0.1/vgg.pth as in docs/evaluation.md)";
}

}  // namespace dojo::eval
