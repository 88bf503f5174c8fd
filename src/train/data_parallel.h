// Data-parallel training over torch.distributed's own runtime (c10d: a TCPStore rendezvous and a
// Gloo process group), so `dojo ... train` runs under `dojo launch`, torchrun, SLURM or by hand on
// several machines with the environment torchrun sets:
//
//   RANK, WORLD_SIZE        this process's rank and the number of processes (unset: a world of 1)
//   LOCAL_RANK              rank on this machine (picks the CUDA device when training on one)
//   MASTER_ADDR/PORT        where rank 0 hosts the store every rank meets at (default 127.0.0.1:29500)
//   GLOO_SOCKET_IFNAME      the network interface Gloo binds (default: loopback when MASTER_ADDR is
//                           loopback, otherwise the interface this machine's hostname resolves to)
//   DOJO_DIST_TIMEOUT       seconds a collective may wait for a peer before every rank stops (600)
//
// What every rank does the same way (the trainers, e.g. train/wm_train.cpp):
//   start        parameters broadcast from rank 0 (a resumed run reads the same checkpoint)
//   batches      step k's global batch is world x accumulate micro-batches; micro-batch j of rank r
//                draws from step_generator(seed, k * shards + r * accumulate + j) (BatchShards), so
//                2 processes see exactly the batches 1 process sees with --accumulate 2, and a world
//                of 1 with no accumulation draws from step_generator(seed, k) as before
//   gradients    averaged over ranks in buckets, after the backward pass or, for the flat-buffer
//                trainers, as it runs (overlapped_average.h); clipping and the optimiser step then
//                see the same gradient on every rank, so parameters stay identical
//   rank 0       alone draws progress, writes curves, checkpoints and summaries; the others log
//                warnings and errors only, and their standard output goes to /dev/null
//   failures     a peer that dies or stops answering makes every collective throw dojo::Error
//                naming the rank and what it waited for; rerunning the command resumes
//
// A world of 1 runs no collective at all: training is bit for bit what it was before this file.
#pragma once

#include <torch/types.h>

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

namespace torch::nn {
class Module;
}
namespace dojo::data {
struct LoaderOptions;
}

namespace dojo::train {

struct ParallelWorld {
  int rank = 0, world = 1, local_rank = 0;
  std::string master_addr = "127.0.0.1";
  int master_port = 29500;
  double timeout_s = 600;        // DOJO_DIST_TIMEOUT
  bool overlap_backward = true;  // DOJO_DIST_OVERLAP=0: all-reduce after the backward pass
};
// The torchrun variables above and the DOJO_DIST_* ones; a malformed or inconsistent one throws
// dojo::Error naming it.
ParallelWorld parallel_world_from_environment();

class DataParallel {
 public:
  // The process-wide group, joined from the environment on the first call (a world of 1 joins
  // nothing). Throws dojo::Error when the rendezvous fails or this build has no Gloo.
  static DataParallel& get();
  ~DataParallel();

  int rank() const { return world_.rank; }
  int world() const { return world_.world; }
  int local_rank() const { return world_.local_rank; }
  bool main() const { return world_.rank == 0; }
  bool active() const { return world_.world > 1; }
  // Whether trainers that can start their all-reduce during the backward pass do (overlapped_average.h).
  bool overlaps_backward() const { return world_.overlap_backward; }

  // Overwrites `tensors` (same shapes on every rank) with rank 0's values.
  void broadcast_from_main(const std::vector<torch::Tensor>& tensors);
  // The same for every parameter and buffer of `module`: how each trainer starts its ranks alike.
  void broadcast_from_main(const torch::nn::Module& module);
  // Averages the gradients of `params` over the ranks, in flat buckets of about `bucket_bytes`
  // reduced concurrently. A gradient no rank computed stays undefined; one computed on some ranks
  // only counts as zero on the others.
  void average_gradients(const std::vector<torch::Tensor>& params, int64_t bucket_bytes = 32 << 20);
  // Starts summing `flat` (contiguous, the same size on every rank) over the ranks in place and
  // returns the function that waits for the sum; every rank must start the same sums in the same
  // order (OverlappedGradientAverage's buckets). `what` names the collective in a failure.
  std::function<void()> start_sum(const torch::Tensor& flat, const std::string& what);
  std::vector<double> mean(std::vector<double> values);  // elementwise over the ranks
  // Every rank's `mine` [n] (the same n and dtype on every rank) copied into out[r] (world tensors
  // of n, e.g. views of one buffer), on every rank. `what` names the collective in a failure.
  void all_gather_into(const torch::Tensor& mine, const std::vector<torch::Tensor>& out,
                       const std::string& what);
  // The same into rank 0's `out` only; the other ranks pass an empty `out` and receive nothing.
  void gather_into_main(const torch::Tensor& mine, const std::vector<torch::Tensor>& out,
                        const std::string& what);
  // Rank 0 runs `work` (e.g. writing a cache) before the others do, which then find its result.
  // Waits without the collective timeout: work may take long; a dead rank 0 still ends the wait.
  void main_first(const std::string& what, const std::function<void()>& work);
  // Every rank waits here until all have arrived, without the collective timeout (the work before
  // may be long, e.g. each rank writing its share of a cache); a launcher stops the rest when one
  // rank dies (dojo launch, torchrun).
  void wait_for_all(const std::string& what);
  // Throws on every rank unless all ranks hold the same `value` (an option that must agree).
  void check_same(const std::string& what, const std::string& value);

 private:
  explicit DataParallel(ParallelWorld world);
  void gather(const torch::Tensor& mine, const std::vector<torch::Tensor>& out, bool to_main,
              const std::string& what);
  struct Group;
  ParallelWorld world_;
  std::unique_ptr<Group> group_;  // null in a world of 1
  int64_t sequence_ = 0;          // names main_first's store keys
};

inline DataParallel& data_parallel() { return DataParallel::get(); }

// How a step's global batch splits into micro-batches across ranks and accumulation.
struct BatchShards {
  int64_t global_batch = 1, micro_batch = 1, accumulate = 1, world = 1, rank = 0;
  int64_t shards() const { return world * accumulate; }
  // The step-generator index of this rank's micro-batch `micro` of step `step`.
  int64_t stream_index(int64_t step, int64_t micro) const {
    return step * shards() + rank * accumulate + micro;
  }
  // Where this rank's micro-batch `micro` starts in a step's global batch, for trainers that draw
  // the whole batch on every rank and keep their rows (distillation: its draws are per step).
  int64_t row_offset(int64_t micro) const { return (rank * accumulate + micro) * micro_batch; }
  // Makes `loader` hand out this rank's micro-batches: micro_batch clips a batch, the runs of
  // `accumulate` batches of the whole stream that are this rank's (data::LoaderOptions::stream_*).
  // A loader resuming at step k starts at its batch k * accumulate.
  void share_stream(data::LoaderOptions& loader) const;
  // Throws dojo::UsageError ("<who>: a batch of 6 does not split into 4 equal micro-batches ...") unless
  // global_batch divides into world x accumulate equal micro-batches.
  static BatchShards plan(int64_t global_batch, int64_t accumulate, const DataParallel& group,
                          const std::string& who);
};

}  // namespace dojo::train
