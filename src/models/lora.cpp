#include "models/lora.h"

#include <torch/torch.h>

#include <algorithm>
#include <map>

#include "core/error.h"
#include "models/released_import.h"

namespace nn = torch::nn;

namespace dojo::models {
namespace {

const std::vector<std::string>& all_targets() {
  static const std::vector<std::string> names = {"q", "k", "v", "o", "mlp1", "mlp2"};
  return names;
}

// A module holding one child "default": what PEFT puts between the layer and the adapter's weight.
struct AdapterSlotImpl : nn::Module {
  explicit AdapterSlotImpl(nn::Linear linear) { register_module("default", std::move(linear)); }
};

}  // namespace

bool LoraConfig::targets_layer(const std::string& short_name) const {
  return enabled() && std::find(targets.begin(), targets.end(), short_name) != targets.end();
}

nlohmann::json LoraConfig::to_json() const {
  return {{"rank", rank}, {"alpha", alpha}, {"targets", targets}};
}

LoraConfig LoraConfig::from_json(const nlohmann::json& j, const std::string& where) {
  DOJO_CHECK(j.is_object(), where + ": 'lora' must be an object {rank, alpha, targets}");
  LoraConfig c;
  DOJO_CHECK(j.contains("rank") && j["rank"].is_number_integer() && j["rank"].get<int64_t>() > 0,
             where + ": lora.rank must be a positive integer");
  c.rank = j["rank"].get<int64_t>();
  if (j.contains("alpha")) {
    DOJO_CHECK(j["alpha"].is_number() && j["alpha"].get<double>() > 0,
               where + ": lora.alpha must be positive");
    c.alpha = j["alpha"].get<double>();
  }
  if (j.contains("targets")) {
    DOJO_CHECK(j["targets"].is_array(), where + ": lora.targets must be a list of names");
    c.targets.clear();
    for (const auto& t : j["targets"]) {
      DOJO_CHECK(t.is_string(), where + ": lora.targets must be a list of names");
      c.targets.push_back(t.get<std::string>());
    }
    std::string list;
    for (const auto& t : c.targets) list += (list.empty() ? "" : ",") + t;
    parse_targets(list);  // validates the names
  }
  return c;
}

std::vector<std::string> LoraConfig::parse_targets(const std::string& list) {
  std::vector<std::string> out;
  size_t begin = 0;
  while (begin <= list.size()) {
    const size_t comma = std::min(list.find(',', begin), list.size());
    const std::string name = list.substr(begin, comma - begin);
    DOJO_CHECK(std::find(all_targets().begin(), all_targets().end(), name) != all_targets().end(),
               "unknown LoRA target '" + name + "' (q, k, v, o, mlp1, mlp2)");
    if (std::find(out.begin(), out.end(), name) == out.end()) out.push_back(name);
    begin = comma + 1;
  }
  return out;
}

LoraAdapter attach_lora(nn::Linear& layer, const std::string& short_name, const LoraConfig& config) {
  LoraAdapter adapter;
  if (!config.targets_layer(short_name)) return adapter;
  const int64_t in = layer->weight.size(1), out = layer->weight.size(0);
  adapter.down = nn::Linear(nn::LinearOptions(in, config.rank).bias(false));  // PyTorch's Linear init
  adapter.up = nn::Linear(nn::LinearOptions(config.rank, out).bias(false));
  {
    torch::NoGradGuard no_grad;
    adapter.up->weight.zero_();  // a fresh adapter leaves the layer as it was
  }
  adapter.scale = config.scale();
  layer->register_module("lora_A", std::make_shared<AdapterSlotImpl>(adapter.down));
  layer->register_module("lora_B", std::make_shared<AdapterSlotImpl>(adapter.up));
  return adapter;
}

bool is_lora_name(const std::string& name) {
  return name.find(".lora_A.") != std::string::npos || name.find(".lora_B.") != std::string::npos;
}

std::pair<NamedTensors, NamedTensors> split_lora(NamedTensors tensors) {
  NamedTensors base, adapters;
  for (auto& item : tensors) (is_lora_name(item.first) ? adapters : base).push_back(std::move(item));
  return {std::move(base), std::move(adapters)};
}

void fold_lora(NamedTensors& base, const NamedTensors& adapters, double alpha, const std::string& source) {
  if (adapters.empty()) return;
  // merge_lora reads PEFT's layout: the adapted layers' weights as "X.base_layer.weight".
  std::map<std::string, bool> adapted;  // X -> seen
  for (const auto& [name, t] : adapters) {
    const auto at = name.find(".lora_A.");
    if (at != std::string::npos) adapted[name.substr(0, at)] = false;
  }
  NamedTensors peft;
  for (auto& [name, t] : base) {
    const std::string layer = name.size() > 7 ? name.substr(0, name.size() - 7) : "";  // "X.weight"
    if (name.size() > 7 && name.compare(name.size() - 7, 7, ".weight") == 0 && adapted.count(layer)) {
      adapted[layer] = true;
      peft.emplace_back(layer + ".base_layer.weight", t);
    } else {
      peft.emplace_back(name, t);
    }
  }
  for (const auto& [layer, seen] : adapted)
    DOJO_CHECK(seen, source + ": LoRA adapter of '" + layer + "' has no base weight '" + layer + ".weight'");
  peft.insert(peft.end(), adapters.begin(), adapters.end());
  merge_lora(peft, alpha, source);
  base = std::move(peft);
}

}  // namespace dojo::models
