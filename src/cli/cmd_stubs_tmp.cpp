#include <CLI/CLI.hpp>
#include "cli/commands.h"
namespace dojo::cli {
void register_video(CLI::App&) {}
void register_sim(CLI::App&) {}
void register_demo(CLI::App&) {}
}
