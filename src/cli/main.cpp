// The `dojo` command: parse, apply global options, run one subcommand inside an error boundary.
#include <torch/torch.h>
#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/blas_kernels.h"
#include "core/error.h"
#include "core/heap.h"
#include "core/log.h"
#include "core/runtime.h"
#ifndef DOJO_ENGINE_ONLY
#include "data/embodiments.h"
#endif

namespace dojo::cli {
namespace {
GlobalOptions g_options;
std::function<int()> g_action;
}  // namespace

const GlobalOptions& global_options() { return g_options; }

int matmul_bound_command_threads(const std::string& command, bool on_cuda) {
  if (g_options.threads > 0 || on_cuda) return threads();
  const int n = matmul_bound_threads();
  if (n < threads())
    LOG_INFO(command, ": ", n, " intra-op thread(s); the BLAS library's own threads use every core inside ",
             "each matmul (--threads N to override)");
  return n;
}
void set_action(std::function<int()> action) { g_action = std::move(action); }

std::filesystem::path default_reference_dir() {
  if (const char* dir = std::getenv("DOJO_REFERENCE"); dir != nullptr && *dir != 0) return dir;
  return std::filesystem::path(DOJO_SOURCE_DIR) / "models" / "reference";
}

std::pair<int64_t, int64_t> parse_size(const std::string& text) {
  const auto x = text.find_first_of("xX");
  try {
    if (x != std::string::npos) {
      size_t used_h = 0, used_w = 0;
      const int64_t h = std::stoll(text.substr(0, x), &used_h);
      const int64_t w = std::stoll(text.substr(x + 1), &used_w);
      if (used_h == x && used_w == text.size() - x - 1 && h > 0 && w > 0) return {h, w};
    }
  } catch (const std::exception&) {
  }
  throw UsageError("--size expects HxW with positive integers (e.g. 256x320), got '" + text + "'");
}

namespace {

size_t edit_distance(const std::string& a, const std::string& b) {
  std::vector<size_t> row(b.size() + 1);
  for (size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (size_t i = 1; i <= a.size(); ++i) {
    size_t diagonal = row[0];
    row[0] = i;
    for (size_t j = 1; j <= b.size(); ++j) {
      const size_t above = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diagonal + (a[i - 1] == b[j - 1] ? 0 : 1)});
      diagonal = above;
    }
  }
  return row[b.size()];
}

// The option `name` (e.g. "--threads" or "-d") of `app` or of a parent it falls through to.
const CLI::Option* find_option(const CLI::App* app, const std::string& name) {
  for (; app != nullptr; app = app->get_parent())
    for (const CLI::Option* o : app->get_options())
      if (o->check_name(name)) return o;
  return nullptr;
}

}  // namespace

// CLI11 reports a mistyped command word vaguely ("A subcommand is required", or the parent's help
// for `dojo nonsense --help`). Walks the command words of argv first: a word where the current
// command expects a subcommand must name one. Throws dojo::UsageError naming it otherwise.
void check_command_words(const CLI::App& app, int argc, char** argv) {
  const CLI::App* current = &app;
  std::string path = "dojo";
  for (int i = 1; i < argc; ++i) {
    const std::string word = argv[i];
    if (word == "--") return;
    if (word.size() > 1 && word[0] == '-') {
      if (word.find('=') != std::string::npos) continue;
      const auto* option = find_option(current, word);
      // An option that takes a value consumes the next word.
      if (option != nullptr && option->get_type_size_max() > 0 && option->get_expected_max() != 0) ++i;
      continue;
    }
    const auto subcommands = current->get_subcommands([](const CLI::App*) { return true; });
    if (subcommands.empty()) return;  // a positional argument of a leaf command
    const CLI::App* next = nullptr;
    for (const CLI::App* sub : subcommands)
      if (sub->check_name(word)) next = sub;
    if (next == nullptr) {
      std::string closest;
      size_t best = 3;  // suggest only near misses
      for (const CLI::App* sub : subcommands) {
        const size_t d = edit_distance(word, sub->get_name());
        if (d < best) best = d, closest = sub->get_name();
      }
      throw UsageError("unknown command '" + path + " " + word + "'" +
                       (closest.empty() ? "" : " (did you mean '" + path + " " + closest + "'?)") +
                       "; see `" + path + " --help`");
    }
    current = next;
    path += " " + next->get_name();
  }
}

}  // namespace dojo::cli

int main(int argc, char** argv) {
  using namespace dojo;
  use_the_cpus_blas_kernels(argv);  // may start this program again, with OPENBLAS_CORETYPE set
  keep_freed_memory_in_the_heap();
  CLI::App app{
      "dojo: DreamDojo.cpp, a C++ engine for generalist robot world models.\n"
      "Run `dojo <command> --help` for the options of a command."};
  app.set_version_flag("--version", version_string() + " (" + git_commit() + ")");
  app.require_subcommand(1);
  app.fallthrough();
  auto& opts = const_cast<cli::GlobalOptions&>(cli::global_options());
  app.add_option("--threads", opts.threads, "Intra-op CPU threads (0 = all cores)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  std::string embodiments;  // read after parsing, before the command runs
#ifndef DOJO_ENGINE_ONLY
  app.add_option("--embodiments", embodiments,
                 "JSON table of your own robots (docs/new_robot.md); default: $DOJO_EMBODIMENTS")
      ->check(CLI::ExistingFile);
#endif
  app.add_flag("-v,--verbose", opts.verbose, "Log debug messages");
  app.add_flag("-q,--quiet", opts.quiet, "Log warnings and errors only");

  cli::register_version(app);
  cli::register_convert(app);
#ifdef DOJO_ENGINE_ONLY
  // The engine-only build (CMake option DOJO_ENGINE_ONLY): the streaming engine's timing alone.
  auto* wm = app.add_subcommand("wm", "Action-conditioned world model (DiT, rectified flow)");
  wm->require_subcommand(1);
  cli::register_wm_speed(*wm);
#else
  cli::register_ckpt(app);
  cli::register_video(app);
  cli::register_bench(app);
#ifdef DOJO_WITH_SIM
  cli::register_sim(app);
#endif
  cli::register_data(app);
  cli::register_tokenizer(app);
#ifdef DOJO_WITH_SIM
  cli::register_demo(app);
  cli::register_policy(app);
  cli::register_plan(app);
  cli::register_serve_check(app);
#endif
  cli::register_lam(app);
  cli::register_wm(app);
  cli::register_distill(app);
#ifdef DOJO_WITH_MEDIA
  cli::register_serve(app);
  cli::register_study(app);
  cli::register_serve_load(app);
#endif
  cli::register_launch(app);
  cli::register_metrics(app);
  cli::register_probe(app);
#endif

  try {
    cli::check_command_words(app, argc, argv);
    app.parse(argc, argv);
  } catch (const UsageError& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 2;
  } catch (const CLI::ParseError& e) {
    // --help and --version are "errors" that exit 0; real usage errors exit 2.
    const int code = app.exit(e);
    return code == 0 ? 0 : 2;
  }

  try {
    if (opts.verbose) set_log_level(LogLevel::kDebug);
    if (opts.quiet) set_log_level(LogLevel::kWarn);
    set_threads(opts.threads);
#ifndef DOJO_ENGINE_ONLY
    if (const char* env = std::getenv("DOJO_EMBODIMENTS"); embodiments.empty() && env != nullptr && *env != 0)
      embodiments = env;
    if (!embodiments.empty()) data::load_embodiment_table(embodiments);
#endif
    if (!cli::g_action) return 0;
    return cli::g_action();
  } catch (const UsageError& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 2;
  } catch (const Error& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  } catch (const c10::Error& e) {
    // libtorch messages carry a C++ backtrace; the user needs only the first line.
    std::string message = e.what_without_backtrace();
    const auto newline = message.find('\n');
    if (newline != std::string::npos) message.resize(newline);
    std::fprintf(stderr, "error: %s\n", message.c_str());
    return 1;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
}
