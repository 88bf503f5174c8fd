#include "cli/world_model_args.h"

#include <CLI/CLI.hpp>

#include "cli/commands.h"
#include "cli/model_args.h"
#include "cli/options.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"

namespace fs = std::filesystem;

namespace dojo::cli {
namespace {

fs::path pick(const std::string& given, const fs::path& fallback) {
  return given.empty() ? fallback : fs::path(given);
}

}  // namespace

recipes::WorldModelSource resolve_world_model(const WorldModelArgs& a, const std::string& who) {
  recipes::WorldModelSource s;
  s.teacher = !a.teacher.empty();
  const auto reference = a.demo.empty() && a.student.empty() && !s.teacher ? reference_student() : fs::path();
  if (!reference.empty()) {
    s.checkpoint = reference;
    s.tokenizer = pick(a.tokenizer, default_reference_dir() / "tokenizer");
    s.fast_decoder = reference_model_fast_decoder(a.fast_decoder, !a.tokenizer.empty());
    LOG_INFO(who, ": the reference student ", s.checkpoint.string(),
             s.fast_decoder.empty() ? "" : ", decoded with " + s.fast_decoder.string());
  } else {
    const fs::path demo = a.demo.empty() ? "dojo_demo" : a.demo;
    s.checkpoint = s.teacher ? fs::path(a.teacher) : pick(a.student, demo / "student" / "checkpoint");
    s.tokenizer = pick(a.tokenizer, demo / "tokenizer" / "checkpoint");
    s.fast_decoder = a.fast_decoder;
    if (s.fast_decoder.empty() && a.student.empty() && !s.teacher &&
        fs::exists(demo / "fast_decoder" / "checkpoint"))
      s.fast_decoder = demo / "fast_decoder" / "checkpoint";
  }
  s.device = a.device;
  s.precision = a.precision;
  s.teacher_steps = a.teacher_steps;
  DOJO_CHECK(s.teacher_steps == 0 || s.teacher,
             who + ": --teacher-steps applies to a --teacher world model only (the student takes 4 hops)");
  DOJO_CHECK(checkpoint_exists(s.checkpoint),
             who + ": no world model at " + s.checkpoint.string() +
                 " (give --student or --teacher, or --demo DIR of a finished `dojo demo`)");
  DOJO_CHECK(checkpoint_exists(s.tokenizer), who + ": no tokenizer at " + s.tokenizer.string());
  DOJO_CHECK(s.fast_decoder.empty() || checkpoint_exists(s.fast_decoder),
             who + ": no fast decoder at " + s.fast_decoder.string());
  return s;
}

void add_world_model_options(CLI::App* cmd, WorldModelArgs& wm) {
  cmd->add_option("--demo", wm.demo,
                  "Take the models from this `dojo demo` output (default: the reference set's student "
                  "when the set has one, else dojo_demo)");
  cmd->add_option("--student", wm.student,
                  "Student checkpoint (default: the reference set's, else the demo's)");
  cmd->add_option("--teacher", wm.teacher, "Use this teacher checkpoint instead (12-frame chunks)");
  cmd->add_option("--teacher-steps", wm.teacher_steps,
                  "With --teacher: sampler steps per chunk (default: the trained sampler's, 35)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--tokenizer", wm.tokenizer,
                  "Tokenizer checkpoint (default: the reference set's with its student, else the demo's)");
  cmd->add_option(
      "--fast-decoder", wm.fast_decoder,
      "Student's fast decoder (default: that of the reference set or demo the student comes from, "
      "when it has one)");
  add_device_option(cmd, wm.device);
  add_precision_option(cmd, wm.precision);
}

}  // namespace dojo::cli
