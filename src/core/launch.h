// `dojo launch`: starts one process per rank on this machine with the environment torchrun sets
// (RANK, WORLD_SIZE, LOCAL_RANK, LOCAL_WORLD_SIZE, GROUP_RANK, MASTER_ADDR, MASTER_PORT), watches
// them, and stops the others when one fails, so a dead rank never leaves its peers waiting. The
// ranks meet over torch.distributed's own store and process group (train/data_parallel.h); this
// file only starts and supervises processes, the same role torchrun's agent plays.
//
// Written here rather than delegating to torchrun: users of the C++ engine need no Python, and a
// machine of several nodes runs the same `dojo launch` on each with --nnodes/--node-rank.
#pragma once

#include <string>
#include <vector>

namespace dojo {

struct LaunchOptions {
  int nproc = 1;      // processes on this machine
  int nnodes = 1;     // machines in the job
  int node_rank = 0;  // this machine's index: its ranks are node_rank * nproc + [0, nproc)
  std::string master_addr = "127.0.0.1";
  int master_port = 29500;
  // Intra-op threads of each process when OMP_NUM_THREADS is unset: cores / nproc (at least 1),
  // so the ranks of one machine do not oversubscribe its cores.
  int threads = 0;
  double grace_s = 10;               // after a failure, seconds the others get to exit before SIGKILL
  std::vector<std::string> command;  // argv of each rank; "dojo" runs this very binary
};

// Runs the ranks to completion. Returns 0 when all exit 0; otherwise the exit status of the first
// rank that failed (128 + signal for a killed one), after stopping the rest. Throws dojo::Error
// when a process cannot be started.
int launch_processes(const LaunchOptions& options);

}  // namespace dojo
