#include <CLI/CLI.hpp>
#include <cstdio>
#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/runtime.h"

namespace dojo::cli {

void register_version(CLI::App& app) {
  auto* cmd = app.add_subcommand("version", "Print version, build and runtime facts");
  auto json = std::make_shared<bool>(false);
  add_json_option(cmd, *json);
  cmd->callback([json] {
    set_action([json] {
      const auto info = version_info();
      if (*json) {
        std::printf("%s\n", info.dump(2).c_str());
      } else {
        for (const auto& [key, value] : info.items())
          std::printf("%-18s %s\n", key.c_str(),
                      value.is_string() ? value.get<std::string>().c_str() : value.dump().c_str());
      }
      return 0;
    });
  });
}

}  // namespace dojo::cli
