// The world model `policy detector --world-model`, `policy eval` and `plan` run in: the reference
// set's student unless told otherwise, else the demo's (their shared options).
#pragma once

#include <string>

#include "recipes/policy_eval.h"

namespace CLI {
class App;
}

namespace dojo::cli {

struct WorldModelArgs {
  std::string demo, student, teacher, tokenizer, fast_decoder;  // demo "": dojo_demo
  std::string device = "cpu", precision = "fp32";
  int teacher_steps = 0;  // the teacher's sampler steps (0: the ones it was trained with)
};

// Without --demo, --student or --teacher: the reference set's student (with its tokenizer and fast
// decoder) where the set has one; otherwise the demo's student unless `args` names others. Checks
// that the files exist; `who` starts the error messages.
recipes::WorldModelSource resolve_world_model(const WorldModelArgs& args, const std::string& who);

// --demo, --student, --teacher, --teacher-steps, --tokenizer, --fast-decoder, --device, --precision.
void add_world_model_options(CLI::App* cmd, WorldModelArgs& wm);

}  // namespace dojo::cli
