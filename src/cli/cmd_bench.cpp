#include <CLI/CLI.hpp>
#include <cstdio>
#include <nlohmann/json.hpp>

#include "bench/bench.h"
#include "cli/commands.h"
#include "cli/options.h"

namespace dojo::cli {

void register_bench(CLI::App& app) {
  auto* cmd = app.add_subcommand(
      "bench",
      "Measure throughput (matmul roofline, video decode, sim render, clip loading) and print a "
      "markdown table of mean ± std over repeats after warm-up");
  auto options = std::make_shared<bench::BenchOptions>();
  auto json = std::make_shared<bool>(false);
  auto list = std::make_shared<bool>(false);
  cmd->add_option("--repeats,-r", options->repeats, "Timed repeats per row")->capture_default_str();
  cmd->add_option("--warmup", options->warmup, "Untimed warm-up runs per row")->capture_default_str();
  add_device_option(cmd, options->device);
  cmd->add_option("--only", options->only, "Run only these rows (names from --list)");
  cmd->add_option("--video", options->video_path,
                  "Video file for the decode row (default: a generated clip)");
  add_json_option(cmd, *json);
  cmd->add_flag("--list", *list, "List the row names and exit");
  cmd->callback([=] {
    set_action([=] {
      const auto cases = bench::builtin_cases(*options);
      if (*list) {
        for (const auto& c : cases)
          std::printf("%-24s %-16s %s\n", c.name.c_str(), c.unit.c_str(), c.params.c_str());
        return 0;
      }
      const auto rows = bench::run_cases(cases, *options);
      if (*json)
        std::printf("%s\n", bench::to_json(rows, *options).dump(2).c_str());
      else
        std::printf("%s", bench::to_markdown(rows, *options).c_str());
      return 0;
    });
  });
}

}  // namespace dojo::cli
