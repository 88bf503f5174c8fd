#include <CLI/CLI.hpp>
#include "cli/commands.h"
namespace dojo::cli {
void register_ckpt(CLI::App&) {}
void register_bench(CLI::App&) {}
void register_sim(CLI::App&) {}
void register_data(CLI::App&) {}
void register_demo(CLI::App&) {}
}
