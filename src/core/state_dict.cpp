#include "core/state_dict.h"

#include <fnmatch.h>

#include <functional>
#include <unordered_map>
#include <unordered_set>

#include "core/error.h"

namespace dojo {
namespace {

void collect(const torch::nn::Module& module, const std::string& prefix, NamedTensors& out) {
  for (const auto& item : module.named_parameters(/*recurse=*/false))
    if (item.value().defined()) out.emplace_back(prefix + item.key(), item.value());
  for (const auto& item : module.named_buffers(/*recurse=*/false))
    if (item.value().defined()) out.emplace_back(prefix + item.key(), item.value());
  for (const auto& child : module.named_children()) collect(*child.value(), prefix + child.key() + ".", out);
}

// The shared body: `lookup` returns the source tensor's shape, or null when absent; `fetch`
// returns the tensor itself (only called for names that will be copied).
LoadReport load_impl(torch::nn::Module& module, const std::string& source,
                     const std::vector<std::string>& source_keys,
                     const std::function<const std::vector<int64_t>*(const std::string&)>& lookup,
                     const std::function<torch::Tensor(const std::string&)>& fetch,
                     const LoadOptions& options) {
  auto ignored = [&](const std::string& file_name) {
    for (const auto& pattern : options.ignore)
      if (glob_match(pattern, file_name)) return true;
    return false;
  };

  LoadReport report;
  report.source = source;
  const NamedTensors targets = state_dict(module);
  std::unordered_set<std::string> wanted;                     // file names the module asks for
  std::vector<std::pair<torch::Tensor, std::string>> copies;  // target, file name
  for (const auto& [name, target] : targets) {
    const std::string file_name = options.prefix + name;
    if (ignored(file_name)) continue;
    wanted.insert(file_name);
    const std::vector<int64_t>* shape = lookup(file_name);
    if (shape == nullptr) {
      report.missing.push_back(name);
    } else if (c10::IntArrayRef(*shape) != target.sizes()) {
      report.shape_mismatch.push_back(name + ": expected " + shape_string(target.sizes()) + " got " +
                                      shape_string(*shape));
    } else {
      copies.emplace_back(target, file_name);
      report.loaded.push_back(name);
    }
  }
  for (const auto& key : source_keys) {
    if (key.compare(0, options.prefix.size(), options.prefix) != 0) continue;
    if (ignored(key) || wanted.count(key) != 0) continue;
    report.unexpected.push_back(key);
  }
  if (options.strict && !report.ok())
    throw Error("cannot load " + source + " into the model: " + report.to_string("; "));

  torch::NoGradGuard no_grad;
  for (auto& [target, file_name] : copies) target.copy_(fetch(file_name));
  return report;
}

}  // namespace

NamedTensors state_dict(const torch::nn::Module& module) {
  NamedTensors out;
  collect(module, "", out);
  return out;
}

bool glob_match(const std::string& pattern, const std::string& name) {
  return ::fnmatch(pattern.c_str(), name.c_str(), 0) == 0;
}

std::string LoadReport::to_string(const std::string& separator) const {
  if (ok()) return "ok: " + std::to_string(loaded.size()) + " tensors loaded";
  constexpr size_t kShown = 5;
  std::string text;
  auto add = [&](const char* label, const std::vector<std::string>& names) {
    if (names.empty()) return;
    if (!text.empty()) text += separator;
    text += std::string(label) + " " + std::to_string(names.size()) + ": ";
    for (size_t i = 0; i < names.size() && i < kShown; ++i) text += (i ? ", " : "") + names[i];
    if (names.size() > kShown) text += ", ... (+" + std::to_string(names.size() - kShown) + " more)";
  };
  add("missing", missing);
  add("unexpected", unexpected);
  add("shape mismatch", shape_mismatch);
  return text;
}

LoadReport load_state_dict(torch::nn::Module& module, const SafetensorsFile& file,
                           const LoadOptions& options) {
  return load_impl(
      module, file.path().string(), file.keys(),
      [&](const std::string& name) { return file.contains(name) ? &file.info(name).shape : nullptr; },
      [&](const std::string& name) { return file.tensor(name); }, options);
}

LoadReport load_state_dict(torch::nn::Module& module, const NamedTensors& tensors,
                           const LoadOptions& options) {
  std::unordered_map<std::string, std::pair<std::vector<int64_t>, torch::Tensor>> index;
  std::vector<std::string> keys;
  for (const auto& [name, tensor] : tensors) {
    if (index.emplace(name, std::make_pair(tensor.sizes().vec(), tensor)).second) keys.push_back(name);
  }
  return load_impl(
      module, "tensors", keys,
      [&](const std::string& name) -> const std::vector<int64_t>* {
        const auto it = index.find(name);
        return it == index.end() ? nullptr : &it->second.first;
      },
      [&](const std::string& name) { return index.at(name).second; }, options);
}

}  // namespace dojo
