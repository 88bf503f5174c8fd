// LPIPS-VGG as piq.LPIPS() computes it (what DreamDojo reports; ../shared/reference/metrics.md §4):
// ImageNet mean/std normalisation of [0, 1] input (= the official ScalingLayer on 2x − 1),
// torchvision VGG16 `features` up to relu5_3, taps relu1_2 relu2_2 relu3_3 relu4_3 relu5_3,
// channel-wise unit normalisation (eps 1e-10), squared difference weighted per channel by the
// linear heads, spatial mean, sum over channels and taps.
//
// No weights ship with DreamDojo.cpp (ImageNet VGG16 + the 5 head tensors are downloads); the
// user converts them to safetensors once (docs/evaluation.md) and passes the file(s).
// Accepted tensor names: trunk "features.<i>.{weight,bias}" (torchvision) or
// "net.slice<k>.<i>.{weight,bias}" (official lpips model); heads "lin<k>.model.1.weight" (official
// vgg.pth) or "lin<k>.weight"; "classifier.*" is ignored.
#pragma once

#include <torch/nn/module.h>
#include <torch/nn/modules/container/sequential.h>
#include <torch/types.h>

#include <filesystem>
#include <string>
#include <vector>

namespace dojo::eval {

// One linear head: "lin<k>.model" = (Dropout, 1 × 1 conv to 1 channel without bias), as named in
// the official weights; only the conv weight [1, C, 1, 1] is used.
struct LpipsHeadImpl : torch::nn::Module {
  explicit LpipsHeadImpl(int64_t channels);
  torch::nn::Sequential model{nullptr};
  const torch::Tensor& weight() const;  // [1, C, 1, 1]
};
TORCH_MODULE(LpipsHead);

struct LpipsVggImpl : torch::nn::Module {
  // Random (PyTorch default) initialisation; load real weights with load_lpips_weights().
  LpipsVggImpl();
  // x, y: [N, 3, H, W] float in [0, 1] -> [N] distances (0 for identical images).
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& y);

  torch::nn::Sequential features{nullptr};  // VGG16 features[0:30] (13 convs, 4 max-pools)
  std::vector<LpipsHead> heads;             // lin0 … lin4 over 64, 128, 256, 512, 512 channels
};
TORCH_MODULE(LpipsVgg);

// Loads the trunk and heads from one or more safetensors files (e.g. the VGG16 features in one,
// the heads in another). Throws dojo::Error naming the file(s) and the missing / unexpected /
// misshapen tensors.
void load_lpips_weights(LpipsVgg& net, const std::vector<std::filesystem::path>& files);

// The LPIPS metric: empty (unavailable) until weights are given.
class Lpips {
 public:
  Lpips() = default;
  // Builds the network and loads `files`; throws dojo::Error for a missing file or bad tensors.
  static Lpips load(const std::vector<std::filesystem::path>& files);
  // Wraps an existing network (e.g. random weights in tests).
  static Lpips from_network(LpipsVgg net);

  bool available() const { return static_cast<bool>(net_); }
  // Per-frame LPIPS of frames in metrics.h layouts (uint8 [N, H, W, 3] or float [N, 3, H, W] in
  // [0, 1]) -> [N] float32, computed without autograd on the network's device. Throws dojo::Error
  // saying which weights are missing when !available().
  torch::Tensor per_frame(const torch::Tensor& pred, const torch::Tensor& gt) const;

 private:
  mutable LpipsVgg net_{nullptr};  // forward() is non-const in libtorch; evaluation does not change it
};

// The message thrown when LPIPS is requested without weights (names the flag and the docs).
std::string lpips_missing_weights_message();

}  // namespace dojo::eval
