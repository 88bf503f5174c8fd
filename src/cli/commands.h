// Registration of the `dojo` subcommands. Each command file adds its subcommand(s) to the app
// and sets a callback; main() parses, then runs the selected callback inside one error
// boundary so every failure becomes a one-line message and a non-zero exit.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>
#include <utility>

namespace CLI {
class App;
}

namespace dojo::cli {

// Options every command shares, parsed before any callback runs.
struct GlobalOptions {
  int threads = 0;  // 0 = all cores
  bool verbose = false;
  bool quiet = false;
};

const GlobalOptions& global_options();

// Intra-op threads for a matmul-bound command on `device` (transformer training): the user's
// --threads when given, else matmul_bound_threads() on CPU (core/runtime.h says why), logged.
int matmul_bound_command_threads(const std::string& command, bool on_cuda);

// The reference model set shipped in the repository (models/reference), or the directory named by
// the environment variable DOJO_REFERENCE.
std::filesystem::path default_reference_dir();

// Parses a --size value "HxW" (positive integers) into {H, W}; throws dojo::UsageError.
std::pair<int64_t, int64_t> parse_size(const std::string& text);

// The callback to run once parsing succeeded. Commands set it from their parse callback.
void set_action(std::function<int()> action);

void register_version(CLI::App& app);
void register_ckpt(CLI::App& app);
void register_convert(CLI::App& app);  // engine-only builds too
void register_video(CLI::App& app);
void register_bench(CLI::App& app);
void register_sim(CLI::App& app);
void register_data(CLI::App& app);
void register_demo(CLI::App& app);
void register_lam(CLI::App& app);
void register_tokenizer(CLI::App& app);
void register_fast_decoder(CLI::App& tokenizer);  // `tokenizer fast-decoder`
void register_wm(CLI::App& app);
void register_wm_stream(CLI::App& wm);      // `wm stream`, under register_wm's `wm`
void register_wm_speed(CLI::App& wm);       // `wm speed`, likewise
void register_wm_step_speed(CLI::App& wm);  // `wm step-speed` (DojoSim builds: a recipe)
void register_metrics(CLI::App& app);
void register_probe(CLI::App& app);
void register_distill(CLI::App& app);
void register_serve(CLI::App& app);
void register_study(CLI::App& app);
void register_serve_load(CLI::App& app);
void register_launch(CLI::App& app);       // dojo launch: data-parallel processes
void register_serve_check(CLI::App& app);  // DojoSim builds only
void register_policy(CLI::App& app);       // DojoSim builds only
void register_plan(CLI::App& app);         // `value train` and `plan`; DojoSim builds only

}  // namespace dojo::cli
