// State dicts of torch::nn::Module: named parameters and buffers out, checked loading in.
#pragma once

#include <torch/torch.h>

#include <string>
#include <vector>

#include "core/safetensors.h"

namespace dojo {

// Parameters and (defined) buffers with dotted names, in PyTorch's state_dict order: each
// module's own parameters, then its own buffers, then its children in registration order.
// The tensors are the module's own (not copies).
NamedTensors state_dict(const torch::nn::Module& module);

struct LoadOptions {
  // Missing, unexpected or misshapen tensors throw dojo::Error (nothing is copied then).
  // Non-strict: they are only reported, and every tensor that matches is copied.
  bool strict = true;
  // The file names tensors prefix + module name, e.g. prefix "net." loads "net.blocks.0.w" into
  // "blocks.0.w". File tensors without the prefix belong to something else and are not
  // reported as unexpected.
  std::string prefix;
  // Glob patterns ('*' matches any run of characters, '?' one character) over file-side names
  // (prefix included) to leave out on both sides, e.g. "*._extra_state", "net.accum_*".
  std::vector<std::string> ignore;
};

struct LoadReport {
  std::string source;                       // the file (or "tensors") loaded from
  std::vector<std::string> loaded;          // module names copied
  std::vector<std::string> missing;         // module names with no tensor in the source
  std::vector<std::string> unexpected;      // source names with no module tensor
  std::vector<std::string> shape_mismatch;  // "name: expected [a, b] got [c, d]"

  bool ok() const { return missing.empty() && unexpected.empty() && shape_mismatch.empty(); }
  // One line per non-empty category, "missing 3: a, b, c", at most the first 5 names each
  // (then "... (+N more)"); lines joined by `separator`. "ok: N tensors loaded" when ok().
  std::string to_string(const std::string& separator = "\n") const;
};

// Copies tensors into the module's parameters and buffers (no autograd; dtype converted, e.g.
// a BF16 file into F32 parameters; device kept as the module's). Reports mismatches by name.
LoadReport load_state_dict(torch::nn::Module& module, const SafetensorsFile& file,
                           const LoadOptions& options = {});
LoadReport load_state_dict(torch::nn::Module& module, const NamedTensors& tensors,
                           const LoadOptions& options = {});

// True when `name` matches the glob `pattern` ('*' any run, '?' any one character).
bool glob_match(const std::string& pattern, const std::string& name);

}  // namespace dojo
