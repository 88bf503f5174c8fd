// The `dojo` command: parse, apply global options, run one subcommand inside an error boundary.
#include <torch/torch.h>
#include <CLI/CLI.hpp>
#include <cstdio>

#include "cli/commands.h"
#include "core/error.h"
#include "core/log.h"
#include "core/runtime.h"

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

}  // namespace dojo::cli

int main(int argc, char** argv) {
  using namespace dojo;
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
  app.add_flag("-v,--verbose", opts.verbose, "Log debug messages");
  app.add_flag("-q,--quiet", opts.quiet, "Log warnings and errors only");

  cli::register_version(app);
  cli::register_ckpt(app);
  cli::register_video(app);
  cli::register_bench(app);
#ifdef DOJO_WITH_SIM
  cli::register_sim(app);
#endif
  cli::register_data(app);
  cli::register_tokenizer(app);
  cli::register_demo(app);
  cli::register_lam(app);
  cli::register_wm(app);
  cli::register_metrics(app);

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help and --version are "errors" that exit 0; real usage errors exit 2.
    const int code = app.exit(e);
    return code == 0 ? 0 : 2;
  }

  try {
    if (opts.verbose) set_log_level(LogLevel::kDebug);
    if (opts.quiet) set_log_level(LogLevel::kWarn);
    set_threads(opts.threads);
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
