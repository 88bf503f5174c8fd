#include "core/launch.h"

#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <thread>

#include "core/error.h"
#include "core/log.h"

namespace dojo {
namespace {

std::atomic<int> g_forwarded_signal{0};

void remember_signal(int signal) { g_forwarded_signal = signal; }

// The status a shell would report: the exit code, or 128 + the signal that killed it.
int exit_status(int status) {
  if (WIFEXITED(status)) return WEXITSTATUS(status);
  if (WIFSIGNALED(status)) return 128 + WTERMSIG(status);
  return 1;
}

std::string describe(int status) {
  if (WIFSIGNALED(status)) return std::string("was killed by signal ") + strsignal(WTERMSIG(status));
  return "exited with status " + std::to_string(exit_status(status));
}

[[noreturn]] void exec_rank(const LaunchOptions& o, int local_rank) {
  // The rank dies with its launcher instead of lingering as an orphan holding a port, and leads
  // a process group of its own, so stopping it stops what it started (a shell's children too).
  prctl(PR_SET_PDEATHSIG, SIGTERM);
  setpgid(0, 0);
  const int rank = o.node_rank * o.nproc + local_rank;
  setenv("RANK", std::to_string(rank).c_str(), 1);
  setenv("WORLD_SIZE", std::to_string(o.nnodes * o.nproc).c_str(), 1);
  setenv("LOCAL_RANK", std::to_string(local_rank).c_str(), 1);
  setenv("LOCAL_WORLD_SIZE", std::to_string(o.nproc).c_str(), 1);
  setenv("GROUP_RANK", std::to_string(o.node_rank).c_str(), 1);
  setenv("MASTER_ADDR", o.master_addr.c_str(), 1);
  setenv("MASTER_PORT", std::to_string(o.master_port).c_str(), 1);
  int threads = o.threads;
  if (threads <= 0) {
    const unsigned cores = std::thread::hardware_concurrency();
    threads = std::max(1, static_cast<int>(cores) / std::max(1, o.nproc));
  }
  setenv("OMP_NUM_THREADS", std::to_string(threads).c_str(), 0);  // the user's value wins
  setenv("OPENBLAS_NUM_THREADS", std::to_string(threads).c_str(), 0);
  std::vector<std::string> args = o.command;
  std::string program = args[0];
  if (program == "dojo") program = "/proc/self/exe";  // this binary, wherever it was started from
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  execvp(program.c_str(), argv.data());
  std::fprintf(stderr, "[ERROR] dojo launch: rank %d could not run %s: %s\n", rank, args[0].c_str(),
               std::strerror(errno));
  _exit(127);
}

}  // namespace

int launch_processes(const LaunchOptions& o) {
  if (o.command.empty())
    throw UsageError("dojo launch: no command given (dojo launch --nproc N -- dojo ...)");
  if (o.nproc < 1 || o.nnodes < 1 || o.node_rank < 0 || o.node_rank >= o.nnodes)
    throw UsageError("dojo launch: need --nproc >= 1, --nnodes >= 1 and 0 <= --node-rank < --nnodes");
  if (o.master_port < 1 || o.master_port > 65535)
    throw UsageError("dojo launch: --master-port must be in [1, 65535]");

  // Ctrl-C and a scheduler's SIGTERM reach the ranks too; the launcher waits for them to stop.
  struct sigaction forward {};
  forward.sa_handler = remember_signal;
  sigemptyset(&forward.sa_mask);
  struct sigaction old_int {
  }, old_term{};
  sigaction(SIGINT, &forward, &old_int);
  sigaction(SIGTERM, &forward, &old_term);

  std::vector<pid_t> pids(static_cast<size_t>(o.nproc), -1);
  for (int i = 0; i < o.nproc; ++i) {
    const pid_t pid = fork();
    if (pid < 0) {
      for (pid_t p : pids)
        if (p > 0) kill(p, SIGKILL);
      throw Error(std::string("dojo launch: fork failed: ") + std::strerror(errno));
    }
    if (pid == 0) exec_rank(o, i);
    setpgid(pid, pid);  // also here: whichever of parent and child runs first
    pids[static_cast<size_t>(i)] = pid;
  }
  LOG_INFO("dojo launch: ", o.nproc, " processes (ranks ", o.node_rank * o.nproc, "-",
           o.node_rank * o.nproc + o.nproc - 1, " of ", o.nnodes * o.nproc, ") meeting at ", o.master_addr,
           ":", o.master_port);

  int running = o.nproc, result = 0;
  bool stopping = false;
  std::chrono::steady_clock::time_point kill_at;
  // A rank's whole process group, or the rank alone when it has none of its own.
  const auto signal_rank = [](pid_t p, int signal) {
    if (kill(-p, signal) != 0) kill(p, signal);
  };
  const auto stop_all = [&](int signal) {
    for (pid_t p : pids)
      if (p > 0) signal_rank(p, signal);
    if (!stopping)
      kill_at = std::chrono::steady_clock::now() +
                std::chrono::milliseconds(static_cast<int64_t>(o.grace_s * 1000));
    stopping = true;
  };
  while (running > 0) {
    if (const int signal = g_forwarded_signal.exchange(0); signal != 0) {
      LOG_WARN("dojo launch: ", strsignal(signal), "; stopping every rank");
      if (result == 0) result = 128 + signal;
      stop_all(signal);
    }
    int status = 0;
    const pid_t pid = waitpid(-1, &status, WNOHANG);
    if (pid > 0) {
      for (size_t i = 0; i < pids.size(); ++i) {
        if (pids[i] != pid) continue;
        pids[i] = -1;
        --running;
        const int code = exit_status(status);
        if (code != 0 && result == 0) {
          result = code;
          LOG_ERROR("dojo launch: rank ", o.node_rank * o.nproc + static_cast<int>(i), " ", describe(status),
                    "; stopping the other ", running,
                    " (rerun the same command to resume from the last checkpoint)");
          if (!stopping) stop_all(SIGTERM);
        }
      }
      continue;
    }
    if (pid < 0 && errno != EINTR) break;
    if (stopping && std::chrono::steady_clock::now() > kill_at) {
      for (pid_t p : pids)
        if (p > 0) signal_rank(p, SIGKILL);
      kill_at = std::chrono::steady_clock::time_point::max();  // killed: only the reaping is left
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  sigaction(SIGINT, &old_int, nullptr);
  sigaction(SIGTERM, &old_term, nullptr);
  return result;
}

}  // namespace dojo
