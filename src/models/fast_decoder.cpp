#include "models/fast_decoder.h"

#include <torch/torch.h>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/state_dict.h"

namespace nn = torch::nn;

namespace dojo::models {

namespace {

nn::Conv2d conv3x3(int64_t in, int64_t out) { return nn::Conv2d(nn::Conv2dOptions(in, out, 3).padding(1)); }

torch::Tensor upsample2x(const torch::Tensor& x) {  // nearest, [B, C, H, W] -> [B, C, 2H, 2W]
  return at::upsample_nearest2d(x, {x.size(2) * 2, x.size(3) * 2});
}

}  // namespace

nlohmann::json FastDecoderConfig::to_json() const {
  return {{"latent_channels", latent_channels},
          {"widths", widths},
          {"blocks", blocks},
          {"head_width", head_width}};
}

FastDecoderConfig FastDecoderConfig::from_json(const nlohmann::json& j) {
  FastDecoderConfig c;
  try {
    c.latent_channels = j.value("latent_channels", c.latent_channels);
    c.widths = j.value("widths", c.widths);
    c.blocks = j.value("blocks", c.blocks);
    c.head_width = j.value("head_width", c.head_width);
  } catch (const nlohmann::json::exception& e) {
    throw Error(std::string("fast decoder config: ") + e.what());
  }
  DOJO_CHECK(c.widths.size() == 3 && c.blocks.size() == 3,
             "fast decoder config: 'widths' and 'blocks' need 3 entries");
  for (auto w : c.widths) DOJO_CHECK(w > 0, "fast decoder config: 'widths' must be positive");
  for (auto b : c.blocks) DOJO_CHECK(b >= 0, "fast decoder config: 'blocks' must be >= 0");
  DOJO_CHECK(c.head_width > 0 && c.latent_channels > 0, "fast decoder config: widths must be positive");
  return c;
}

MemoryBlockImpl::MemoryBlockImpl(int64_t channels) {
  conv1 = register_module("conv1", conv3x3(2 * channels, channels));
  conv2 = register_module("conv2", conv3x3(channels, channels));
}

torch::Tensor MemoryBlockImpl::forward(const torch::Tensor& x, const torch::Tensor& past) {
  const auto prev = past.defined() ? past : torch::zeros_like(x);
  return torch::relu(conv2(torch::relu(conv1(torch::cat({x, prev}, 1)))) + x);
}

FastDecoderImpl::FastDecoderImpl(FastDecoderConfig config) : config_(std::move(config)) {
  const auto& w = config_.widths;
  input = register_module("input", conv3x3(config_.latent_channels, w[0]));
  stages = register_module("stages", nn::ModuleList());
  grow = register_module("grow", nn::ModuleList());
  for (size_t s = 0; s < 3; ++s) {
    nn::ModuleList blocks;
    for (int64_t b = 0; b < config_.blocks[s]; ++b) blocks->push_back(MemoryBlock(w[s]));
    stages->push_back(blocks);
    // Time grows 2x after the first two stages: one 1x1 conv makes both frames' channels.
    if (s < 2) grow->push_back(nn::Conv2d(nn::Conv2dOptions(w[s], 2 * w[s + 1], 1)));
  }
  head1 = register_module("head1", conv3x3(w[2], config_.head_width));
  head2 = register_module("head2", conv3x3(config_.head_width, 3));
}

torch::Tensor FastDecoderImpl::step(const torch::Tensor& z, FastDecoderState& state) {
  DOJO_CHECK(
      z.dim() == 4 && z.size(1) == config_.latent_channels,
      "fast decoder: a latent frame must be [B, " + std::to_string(config_.latent_channels) + ", h, w]");
  std::vector<torch::Tensor> frames = {torch::relu(input(z))};  // [B, w0, h, w]
  size_t slot = 0;
  for (size_t s = 0; s < 3; ++s) {
    const auto& blocks = stages[s]->as<nn::ModuleList>();
    const size_t first_slot = slot;
    // Frame by frame, so each block's memory is its own input one frame earlier.
    for (auto& frame : frames) {
      slot = first_slot;
      for (const auto& block : *blocks) {
        if (state.past.size() <= slot) state.past.resize(slot + 1);
        const auto input_now = frame;
        frame = block->as<MemoryBlock>()->forward(frame, state.past[slot]);
        state.past[slot++] = input_now.detach();
      }
    }
    slot = first_slot + blocks->size();
    if (s < 2) {
      std::vector<torch::Tensor> grown;
      for (const auto& frame : frames) {
        const auto pair = torch::relu(grow[s]->as<nn::Conv2d>()->forward(upsample2x(frame))).chunk(2, 1);
        grown.push_back(pair[0]);  // the earlier of the two frames
        grown.push_back(pair[1]);
      }
      frames.swap(grown);
    }
  }
  std::vector<torch::Tensor> rgb;
  for (const auto& frame : frames)
    rgb.push_back(head2(torch::relu(head1(upsample2x(frame)))));  // [B, 3, 8h, 8w]
  auto out = torch::stack(rgb, 2);                                // [B, 3, 4, H, W]
  if (state.latents_seen++ == 0) out = out.narrow(2, 3, 1);       // the first latent is one frame
  return out;
}

torch::Tensor FastDecoderImpl::decode(const torch::Tensor& z) {
  FastDecoderState state;
  std::vector<torch::Tensor> parts;
  for (int64_t t = 0; t < z.size(2); ++t) parts.push_back(step(z.select(2, t), state));
  return torch::cat(parts, 2);  // [B, 3, 1 + 4 (T − 1), H, W]
}

CheckpointData fast_decoder_checkpoint(const FastDecoderImpl& decoder) {
  CheckpointData data;
  data.config = {{"model", "fast_decoder"}, {"config", decoder.config().to_json()}};
  for (const auto& [name, t] : state_dict(decoder)) data.model.emplace_back("decoder." + name, t);
  return data;
}

FastDecoder load_fast_decoder(const std::filesystem::path& dir) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  const auto& cfg = ckpt.config();
  DOJO_CHECK(
      cfg.value("model", std::string()) == "fast_decoder" && cfg.contains("config"),
      (ckpt.dir() / "config.json").string() + ": not a fast decoder checkpoint (model != fast_decoder)");
  FastDecoder decoder(FastDecoderConfig::from_json(cfg["config"]));
  LoadOptions opts;
  opts.prefix = "decoder.";
  load_state_dict(*decoder, ckpt.model(), opts);
  decoder->eval();
  return decoder;
}

}  // namespace dojo::models
