#include <CLI/CLI.hpp>

#include "cli/commands.h"
#include "core/launch.h"

namespace dojo::cli {

void register_launch(CLI::App& app) {
  auto o = std::make_shared<LaunchOptions>();
  auto* cmd = app.add_subcommand(
      "launch",
      "Run a trainer data-parallel: N processes on this machine (torchrun's environment), stopped together "
      "when one fails. Usage: dojo launch --nproc 2 -- dojo wm train ...");
  cmd->add_option("--nproc,-n", o->nproc, "Processes on this machine")
      ->check(CLI::Range(1, 1024))
      ->capture_default_str();
  cmd->add_option("--nnodes", o->nnodes, "Machines in the job (run dojo launch on each)")
      ->check(CLI::Range(1, 65536))
      ->capture_default_str();
  cmd->add_option("--node-rank", o->node_rank, "This machine's index in [0, --nnodes)")
      ->capture_default_str();
  cmd->add_option("--master-addr", o->master_addr, "Address of the machine with node rank 0")
      ->capture_default_str();
  cmd->add_option("--master-port", o->master_port, "Port rank 0 listens on")->capture_default_str();
  cmd->add_option("--threads-per-process", o->threads,
                  "Intra-op threads of each process when OMP_NUM_THREADS is unset (0: cores / nproc)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cmd->add_option("--grace", o->grace_s, "Seconds the other ranks get to exit after one fails")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cmd->add_option("command", o->command, "The command each rank runs, after --")->required();
  cmd->callback([o] { set_action([o] { return launch_processes(*o); }); });
}

}  // namespace dojo::cli
