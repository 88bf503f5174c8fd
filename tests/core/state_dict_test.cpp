// State dicts of nested torch::nn modules: names and order, round trips through safetensors,
// dtype conversion, and reports of missing / unexpected / misshapen tensors.
#include "core/state_dict.h"

#include "core/error.h"
#include "test_util.h"

namespace dojo {
namespace {

struct BlockImpl : torch::nn::Module {
  BlockImpl() {
    lin = register_module("lin", torch::nn::Linear(8, 4));
    norm = register_module("norm", torch::nn::LayerNorm(torch::nn::LayerNormOptions({4})));
    running = register_buffer("running", torch::zeros({4}));
  }
  torch::nn::Linear lin{nullptr};
  torch::nn::LayerNorm norm{nullptr};
  torch::Tensor running;
};
TORCH_MODULE(Block);

struct NetImpl : torch::nn::Module {
  NetImpl() {
    scale = register_parameter("scale", torch::ones({1}));
    counter = register_buffer("counter", torch::zeros({}, torch::kInt64));
    embed = register_module("embed", torch::nn::Linear(3, 8));
    blocks = register_module("blocks", torch::nn::ModuleList(Block(), Block()));
  }
  torch::Tensor scale, counter;
  torch::nn::Linear embed{nullptr};
  torch::nn::ModuleList blocks{nullptr};
};
TORCH_MODULE(Net);

std::vector<std::string> names(const NamedTensors& tensors) {
  std::vector<std::string> out;
  for (const auto& item : tensors) out.push_back(item.first);
  return out;
}

NamedTensors without(NamedTensors tensors, const std::string& name) {
  tensors.erase(
      std::remove_if(tensors.begin(), tensors.end(), [&](const auto& item) { return item.first == name; }),
      tensors.end());
  return tensors;
}

TEST(StateDict, NamesFollowPyTorchOrder) {
  Net net;
  const std::vector<std::string> expected = {"scale",
                                             "counter",
                                             "embed.weight",
                                             "embed.bias",
                                             "blocks.0.running",
                                             "blocks.0.lin.weight",
                                             "blocks.0.lin.bias",
                                             "blocks.0.norm.weight",
                                             "blocks.0.norm.bias",
                                             "blocks.1.running",
                                             "blocks.1.lin.weight",
                                             "blocks.1.lin.bias",
                                             "blocks.1.norm.weight",
                                             "blocks.1.norm.bias"};
  EXPECT_EQ(names(state_dict(*net)), expected);
  // The tensors are the module's own.
  EXPECT_EQ(state_dict(*net)[2].second.data_ptr(), net->embed->weight.data_ptr());
}

TEST(StateDict, RoundTripThroughSafetensors) {
  torch::manual_seed(1);
  test::TempDir dir;
  Net source;
  {
    torch::NoGradGuard no_grad;
    source->counter.fill_(41);
    source->blocks[1]->as<Block>()->running.normal_();
  }
  save_safetensors(dir / "net.safetensors", state_dict(*source));

  Net target;
  const auto report = load_state_dict(*target, SafetensorsFile::open(dir / "net.safetensors"));
  EXPECT_TRUE(report.ok()) << report.to_string();
  EXPECT_EQ(report.loaded.size(), 14u);
  const auto a = state_dict(*source), b = state_dict(*target);
  for (size_t i = 0; i < a.size(); ++i) EXPECT_TRUE(torch::equal(a[i].second, b[i].second)) << a[i].first;
  EXPECT_TRUE(target->embed->weight.requires_grad());  // still a trainable parameter
}

TEST(StateDict, Bf16FileLoadsIntoFloatModule) {
  Net source, target;
  NamedTensors bf16;
  for (const auto& [name, tensor] : state_dict(*source))
    bf16.emplace_back(name, tensor.is_floating_point() ? tensor.to(torch::kBFloat16) : tensor);
  test::TempDir dir;
  save_safetensors(dir / "bf16.safetensors", bf16);
  load_state_dict(*target, SafetensorsFile::open(dir / "bf16.safetensors"));
  EXPECT_EQ(target->embed->weight.scalar_type(), torch::kFloat32);
  EXPECT_TRUE(
      torch::equal(target->embed->weight, source->embed->weight.to(torch::kBFloat16).to(torch::kFloat32)));
}

TEST(StateDict, StrictLoadNamesMissingUnexpectedAndMisshapenKeys) {
  Net source, target;
  const torch::Tensor before = target->embed->weight.clone();

  auto tensors = without(state_dict(*source), "blocks.1.norm.bias");
  std::string text = test::error_message([&] { load_state_dict(*target, tensors); });
  EXPECT_NE(text.find("missing 1: blocks.1.norm.bias"), std::string::npos) << text;

  tensors = state_dict(*source);
  tensors.emplace_back("blocks.2.lin.weight", torch::zeros({4, 8}));
  text = test::error_message([&] { load_state_dict(*target, tensors); });
  EXPECT_NE(text.find("unexpected 1: blocks.2.lin.weight"), std::string::npos) << text;

  tensors = state_dict(*source);
  for (auto& [name, tensor] : tensors)
    if (name == "blocks.0.lin.weight") tensor = torch::zeros({8, 4});
  test::TempDir dir;
  save_safetensors(dir / "bad.safetensors", tensors);
  text =
      test::error_message([&] { load_state_dict(*target, SafetensorsFile::open(dir / "bad.safetensors")); });
  EXPECT_NE(text.find("shape mismatch 1: blocks.0.lin.weight: expected [4, 8] got [8, 4]"), std::string::npos)
      << text;
  EXPECT_NE(text.find("bad.safetensors"), std::string::npos) << text;
  EXPECT_EQ(text.find('\n'), std::string::npos) << text;

  // A failed strict load changes nothing.
  EXPECT_TRUE(torch::equal(target->embed->weight, before));
}

TEST(StateDict, NonStrictLoadReportsAndCopiesTheRest) {
  Net source, target;
  auto tensors = without(state_dict(*source), "scale");
  for (auto& [name, tensor] : tensors)
    if (name == "embed.bias") tensor = torch::zeros({9});
  tensors.emplace_back("extra", torch::zeros({1}));
  LoadOptions options;
  options.strict = false;
  const torch::Tensor embed_bias = target->embed->bias.clone();
  const auto report = load_state_dict(*target, tensors, options);
  EXPECT_EQ(report.missing, std::vector<std::string>{"scale"});
  EXPECT_EQ(report.unexpected, std::vector<std::string>{"extra"});
  EXPECT_EQ(report.shape_mismatch, std::vector<std::string>{"embed.bias: expected [8] got [9]"});
  EXPECT_EQ(report.loaded.size(), 12u);
  EXPECT_TRUE(torch::equal(target->embed->weight, source->embed->weight));
  EXPECT_TRUE(torch::equal(target->embed->bias, embed_bias));
  EXPECT_EQ(report.to_string(),
            "missing 1: scale\nunexpected 1: extra\nshape mismatch 1: embed.bias: expected [8] got [9]");
}

TEST(StateDict, PrefixAndIgnorePatterns) {
  Net source, target;
  NamedTensors tensors;
  for (const auto& [name, tensor] : state_dict(*source)) tensors.emplace_back("net." + name, tensor);
  tensors.emplace_back("net.accum_iteration", torch::zeros({}, torch::kInt64));
  tensors.emplace_back("net.blocks.0._extra_state", torch::zeros({0}, torch::kUInt8));
  tensors.emplace_back("vae.encoder.weight", torch::zeros({2}));  // another model's tensors: not ours

  LoadOptions options;
  options.prefix = "net.";
  EXPECT_NE(test::error_message([&] {
              load_state_dict(*target, tensors, options);
            }).find("unexpected 2: net.accum_iteration, net.blocks.0._extra_state"),
            std::string::npos);
  options.ignore = {"net.accum_*", "*._extra_state"};
  const auto report = load_state_dict(*target, tensors, options);
  EXPECT_TRUE(report.ok()) << report.to_string();
  EXPECT_TRUE(
      torch::equal(target->blocks[0]->as<Block>()->lin->weight, source->blocks[0]->as<Block>()->lin->weight));

  // Patterns drop module-side names too (as they would be named in the file).
  options.ignore = {"net.blocks.1.*", "net.accum_*", "*._extra_state"};
  auto partial = tensors;
  partial.erase(std::remove_if(partial.begin(), partial.end(),
                               [](const auto& item) { return item.first.rfind("net.blocks.1.", 0) == 0; }),
                partial.end());
  EXPECT_TRUE(load_state_dict(*target, partial, options).ok());
}

TEST(StateDict, ReportListsTheFirstFewNames) {
  LoadReport report;
  for (int i = 0; i < 8; ++i) report.missing.push_back("w" + std::to_string(i));
  EXPECT_EQ(report.to_string(), "missing 8: w0, w1, w2, w3, w4, ... (+3 more)");
  EXPECT_TRUE(glob_match("net.accum_*", "net.accum_iteration"));
  EXPECT_TRUE(glob_match("*._extra_state", "a.b._extra_state"));
  EXPECT_FALSE(glob_match("net.accum_*", "net.blocks.0.accum_x"));
}

TEST(StateDict, LoadsIntoCudaModule_CUDA) {
  DOJO_REQUIRE_CUDA();
  Net source, target;
  target->to(torch::kCUDA);
  test::TempDir dir;
  save_safetensors(dir / "net.safetensors", state_dict(*source));
  load_state_dict(*target, SafetensorsFile::open(dir / "net.safetensors"));
  EXPECT_TRUE(target->embed->weight.is_cuda());
  EXPECT_TRUE(torch::equal(target->embed->weight.cpu(), source->embed->weight));
}

}  // namespace
}  // namespace dojo
