#include <CLI/CLI.hpp>
#include "cli/commands.h"
namespace dojo::cli {
void register_video(CLI::App&) {}
}
