#include "train/data_parallel.h"

// The Gloo process group's header is empty unless USE_C10D_GLOO is defined; Debian's libtorch and
// PyTorch's wheels both build it in. A libtorch shipped without Gloo's headers builds without it
// and refuses a world larger than 1.
#if __has_include(<gloo/algorithm.h>) && __has_include(<torch/csrc/distributed/c10d/ProcessGroupGloo.hpp>)
#define DOJO_HAVE_GLOO 1
#ifndef USE_C10D_GLOO
#define USE_C10D_GLOO
#endif
#include <torch/csrc/distributed/c10d/ProcessGroupGloo.hpp>
#include <torch/csrc/distributed/c10d/TCPStore.hpp>
#endif

#include <torch/torch.h>

#include <cstdio>
#include <cstdlib>
#include <mutex>

#include "core/error.h"
#include "core/log.h"
#include "data/clip_loader.h"

namespace dojo::train {
namespace {

std::string env_or(const char* name, const std::string& fallback) {
  const char* value = std::getenv(name);
  return value && *value ? std::string(value) : fallback;
}

int64_t env_integer(const char* name, int64_t fallback, int64_t low, int64_t high) {
  const auto text = env_or(name, "");
  if (text.empty()) return fallback;
  size_t used = 0;
  int64_t value = 0;
  try {
    value = std::stoll(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  if (used != text.size() || value < low || value > high)
    throw Error("environment: " + std::string(name) + "=" + text + " is not an integer in [" +
                std::to_string(low) + ", " + std::to_string(high) + "]");
  return value;
}

}  // namespace

ParallelWorld parallel_world_from_environment() {
  ParallelWorld w;
  w.world = static_cast<int>(env_integer("WORLD_SIZE", 1, 1, 1 << 16));
  // One process: nothing else is read (a RANK left in the environment by something else is not ours).
  if (w.world == 1) return w;
  w.rank = static_cast<int>(env_integer("RANK", 0, 0, w.world - 1));
  w.local_rank = static_cast<int>(env_integer("LOCAL_RANK", w.rank, 0, w.world - 1));
  w.master_addr = env_or("MASTER_ADDR", w.master_addr);
  w.master_port = static_cast<int>(env_integer("MASTER_PORT", w.master_port, 1, 65535));
  w.timeout_s = static_cast<double>(env_integer("DOJO_DIST_TIMEOUT", 600, 1, 7 * 24 * 3600));
  w.overlap_backward = env_integer("DOJO_DIST_OVERLAP", 1, 0, 1) == 1;
  return w;
}

#ifdef DOJO_HAVE_GLOO
struct DataParallel::Group {
  c10::intrusive_ptr<c10d::TCPStore> store;
  c10::intrusive_ptr<c10d::ProcessGroupGloo> gloo;
};
#else
struct DataParallel::Group {};
#endif

namespace {

// A collective that failed: a peer closed its connection (it died) or did not answer in time.
[[noreturn]] void peer_lost(const ParallelWorld& w, const std::string& what, const std::exception& e) {
  std::string detail = e.what();
  if (const auto eol = detail.find('\n'); eol != std::string::npos) detail.resize(eol);
  throw Error("data parallel (rank " + std::to_string(w.rank) + " of " + std::to_string(w.world) +
              "): " + what + " failed: a peer died or did not answer within DOJO_DIST_TIMEOUT=" +
              std::to_string(static_cast<int64_t>(w.timeout_s)) + " s (" + detail +
              "); rerun the same command to resume from the last checkpoint");
}

}  // namespace

DataParallel& DataParallel::get() {
  static std::once_flag once;
  static std::unique_ptr<DataParallel> instance;
  std::call_once(once, [] { instance.reset(new DataParallel(parallel_world_from_environment())); });
  return *instance;
}

DataParallel::~DataParallel() = default;

DataParallel::DataParallel(ParallelWorld world) : world_(std::move(world)) {
  if (world_.world == 1) return;
#ifndef DOJO_HAVE_GLOO
  throw Error("data parallel: WORLD_SIZE=" + std::to_string(world_.world) +
              " but this build of dojo has no Gloo (its libtorch shipped without the c10d Gloo headers)");
#else
  const auto timeout = std::chrono::milliseconds(static_cast<int64_t>(world_.timeout_s * 1000));
  group_ = std::make_unique<Group>();
  try {
    c10d::TCPStoreOptions options;
    options.port = static_cast<uint16_t>(world_.master_port);
    options.isServer = world_.rank == 0;
    options.numWorkers = static_cast<size_t>(world_.world);
    options.waitWorkers = true;
    options.timeout = timeout;
    group_->store = c10::make_intrusive<c10d::TCPStore>(world_.master_addr, options);
  } catch (const std::exception& e) {
    throw Error("data parallel (rank " + std::to_string(world_.rank) + " of " + std::to_string(world_.world) +
                "): no rendezvous at MASTER_ADDR=" + world_.master_addr +
                " MASTER_PORT=" + std::to_string(world_.master_port) + " within DOJO_DIST_TIMEOUT (" +
                std::string(e.what()).substr(0, 200) + ")");
  }
  auto options = c10d::ProcessGroupGloo::Options::create(timeout);
  const auto interface = env_or("GLOO_SOCKET_IFNAME", "");
  const bool loopback = world_.master_addr == "localhost" || world_.master_addr.rfind("127.", 0) == 0;
  try {
    if (!interface.empty())
      options->devices.push_back(c10d::ProcessGroupGloo::createDeviceForInterface(interface));
    else if (loopback)
      options->devices.push_back(c10d::ProcessGroupGloo::createDeviceForHostname("127.0.0.1"));
    else
      options->devices.push_back(c10d::ProcessGroupGloo::createDefaultDevice());
    group_->gloo =
        c10::make_intrusive<c10d::ProcessGroupGloo>(group_->store, world_.rank, world_.world, options);
  } catch (const std::exception& e) {
    peer_lost(world_, "joining the Gloo group", e);
  }
  // Only rank 0 speaks below warnings and prints results: N copies of every line help nobody.
  if (world_.rank != 0) {
    if (log_level() < LogLevel::kWarn) set_log_level(LogLevel::kWarn);
    std::fflush(stdout);
    if (std::freopen("/dev/null", "w", stdout) == nullptr)
      LOG_WARN("data parallel: stdout stays open on this rank");
  }
  LOG_INFO("data parallel: ", world_.world, " processes joined at ", world_.master_addr, ":",
           world_.master_port);
#endif
}

void DataParallel::broadcast_from_main(const std::vector<torch::Tensor>& tensors) {
  if (!active()) return;
#ifdef DOJO_HAVE_GLOO
  try {
    torch::NoGradGuard no_grad;
    for (const auto& t : tensors) {
      // Gloo wants contiguous tensors of a type it reduces (no bool: sent as bytes); a parameter
      // normally is one, a view or a mask buffer may not be.
      std::vector<torch::Tensor> one = {t.scalar_type() == torch::kBool ? t.to(torch::kUInt8)
                                        : t.is_contiguous()             ? t
                                                                        : t.contiguous()};
      group_->gloo->broadcast(one)->wait();
      if (!one[0].is_same(t)) t.copy_(one[0]);
    }
  } catch (const Error&) {
    throw;
  } catch (const std::exception& e) {
    peer_lost(world_, "broadcasting the initial parameters", e);
  }
#endif
}

void DataParallel::broadcast_from_main(const torch::nn::Module& module) {
  auto tensors = module.parameters();
  for (const auto& b : module.buffers()) tensors.push_back(b);
  broadcast_from_main(tensors);
}

void DataParallel::average_gradients(const std::vector<torch::Tensor>& params, int64_t bucket_bytes) {
  if (!active()) return;
#ifdef DOJO_HAVE_GLOO
  torch::NoGradGuard no_grad;
  try {
    // Which gradients exist anywhere: a rank that skipped a branch must still add its zeros.
    std::vector<double> defined(params.size());
    for (size_t i = 0; i < params.size(); ++i) defined[i] = params[i].grad().defined() ? 1.0 : 0.0;
    const auto anywhere = mean(std::move(defined));  // > 0 where some rank has the gradient
    std::vector<torch::Tensor> grads;
    for (size_t i = 0; i < params.size(); ++i) {
      if (anywhere[i] == 0) continue;
      auto& p = params[i];
      if (!p.grad().defined()) p.mutable_grad() = torch::zeros_like(p);
      grads.push_back(p.grad());
    }
    // Buckets of one dtype and device, flattened so each is one all-reduce; all are started
    // before any is waited on, so Gloo's threads work on several at once.
    struct Bucket {
      std::vector<torch::Tensor> members;
      std::vector<torch::Tensor> flat;
      c10::intrusive_ptr<c10d::Work> work;
    };
    std::vector<Bucket> buckets;
    int64_t filled = 0;
    for (const auto& g : grads) {
      const int64_t bytes = g.numel() * static_cast<int64_t>(g.element_size());
      const bool fits = !buckets.empty() && filled + bytes <= bucket_bytes &&
                        buckets.back().members.front().scalar_type() == g.scalar_type() &&
                        buckets.back().members.front().device() == g.device();
      if (!fits) buckets.emplace_back(), filled = 0;
      buckets.back().members.push_back(g);
      filled += bytes;
    }
    for (auto& b : buckets) {
      std::vector<torch::Tensor> pieces;
      for (const auto& g : b.members) pieces.push_back(g.reshape({-1}));
      b.flat = {torch::cat(pieces)};
      b.work = group_->gloo->allreduce(b.flat);
    }
    const double scale = 1.0 / static_cast<double>(world_.world);
    for (auto& b : buckets) {
      b.work->wait();
      b.flat[0].mul_(scale);
      int64_t offset = 0;
      for (auto& g : b.members) {
        g.copy_(b.flat[0].narrow(0, offset, g.numel()).view_as(g));
        offset += g.numel();
      }
    }
  } catch (const Error&) {
    throw;
  } catch (const std::exception& e) {
    peer_lost(world_, "the gradient all-reduce", e);
  }
#endif
}

std::function<void()> DataParallel::start_sum(const torch::Tensor& flat, const std::string& what) {
  DOJO_CHECK(flat.is_contiguous(), what + ": the all-reduce needs a contiguous tensor");
  if (!active()) return [] {};
#ifdef DOJO_HAVE_GLOO
  c10::intrusive_ptr<c10d::Work> work;
  try {
    std::vector<torch::Tensor> tensors = {flat};
    work = group_->gloo->allreduce(tensors);
  } catch (const std::exception& e) {
    peer_lost(world_, what, e);
  }
  return [this, work, what] {
    try {
      work->wait();
    } catch (const std::exception& e) {
      peer_lost(world_, what, e);
    }
  };
#else
  return [] {};
#endif
}

void DataParallel::all_gather_into(const torch::Tensor& mine, const std::vector<torch::Tensor>& out,
                                   const std::string& what) {
  gather(mine, out, /*to_main=*/false, what);
}

void DataParallel::gather_into_main(const torch::Tensor& mine, const std::vector<torch::Tensor>& out,
                                    const std::string& what) {
  gather(mine, out, /*to_main=*/true, what);
}

void DataParallel::gather(const torch::Tensor& mine, const std::vector<torch::Tensor>& out, bool to_main,
                          const std::string& what) {
  const bool receives = !to_main || main();
  DOJO_CHECK(static_cast<int>(out.size()) == (receives ? world_.world : 0),
             what + ": one output per receiving rank, none elsewhere");
  if (!active()) {
    out[0].copy_(mine);
    return;
  }
#ifdef DOJO_HAVE_GLOO
  torch::NoGradGuard no_grad;
  try {
    std::vector<torch::Tensor> input = {mine.contiguous()};
    std::vector<std::vector<torch::Tensor>> output;
    if (receives) output.push_back(out);  // Gloo's gather wants none on the other ranks
    if (to_main) {
      c10d::GatherOptions options;
      options.rootRank = 0;
      group_->gloo->gather(output, input, options)->wait();
    } else {
      group_->gloo->allgather(output, input)->wait();
    }
  } catch (const std::exception& e) {
    peer_lost(world_, what, e);
  }
#else
  (void)what;
#endif
}

std::vector<double> DataParallel::mean(std::vector<double> values) {
  if (!active() || values.empty()) return values;
#ifdef DOJO_HAVE_GLOO
  try {
    std::vector<torch::Tensor> t = {torch::tensor(values, torch::kFloat64)};
    group_->gloo->allreduce(t)->wait();
    const auto sum = t[0].contiguous();
    const double* summed = sum.data_ptr<double>();
    for (size_t i = 0; i < values.size(); ++i) values[i] = summed[i] / static_cast<double>(world_.world);
  } catch (const std::exception& e) {
    peer_lost(world_, "averaging step statistics", e);
  }
#endif
  return values;
}

void DataParallel::main_first(const std::string& what, const std::function<void()>& work) {
  if (!active()) return work();
#ifdef DOJO_HAVE_GLOO
  const auto key = "dojo/main_first/" + std::to_string(sequence_++);
  if (main()) {
    work();
    group_->store->set(key, std::vector<uint8_t>{1});
    return;
  }
  try {
    // Rank 0 hosts the store: if it dies, the wait ends with an error instead of a hang.
    group_->store->wait({key}, std::chrono::hours(24 * 7));
  } catch (const std::exception& e) {
    peer_lost(world_, "waiting for rank 0 to finish " + what, e);
  }
  work();
#endif
}

void DataParallel::wait_for_all(const std::string& what) {
  if (!active()) return;
#ifdef DOJO_HAVE_GLOO
  const auto key = "dojo/wait/" + std::to_string(sequence_++) + "/";
  try {
    group_->store->set(key + std::to_string(world_.rank), std::vector<uint8_t>{1});
    std::vector<std::string> keys;
    for (int r = 0; r < world_.world; ++r) keys.push_back(key + std::to_string(r));
    group_->store->wait(keys, std::chrono::hours(24 * 7));
  } catch (const std::exception& e) {
    peer_lost(world_, "waiting for every rank to finish " + what, e);
  }
#endif
}

void DataParallel::check_same(const std::string& what, const std::string& value) {
  if (!active()) return;
#ifdef DOJO_HAVE_GLOO
  // Through the store, so every rank sees every value and all of them stop, not only some.
  const auto key = "dojo/check/" + std::to_string(sequence_++) + "/";
  std::vector<std::string> values;
  try {
    group_->store->set(key + std::to_string(world_.rank), std::vector<uint8_t>(value.begin(), value.end()));
    for (int r = 0; r < world_.world; ++r) {
      const auto bytes = group_->store->get(key + std::to_string(r));
      values.emplace_back(bytes.begin(), bytes.end());
    }
  } catch (const std::exception& e) {
    peer_lost(world_, "comparing " + what, e);
  }
  for (int r = 0; r < world_.world; ++r)
    if (values[r] != value)
      throw Error("data parallel (rank " + std::to_string(world_.rank) + " of " +
                  std::to_string(world_.world) + "): the ranks disagree on " + what + " (rank " +
                  std::to_string(r) + ": " + values[r] + ", this rank: " + value +
                  "); start every rank with the same command");
#endif
}

void BatchShards::share_stream(data::LoaderOptions& loader) const {
  loader.batch_size = static_cast<int>(micro_batch);
  loader.stream_every = shards();
  loader.stream_first = rank * accumulate;
  loader.stream_run = accumulate;
}

BatchShards BatchShards::plan(int64_t global_batch, int64_t accumulate, const DataParallel& group,
                              const std::string& who) {
  BatchShards s;
  s.global_batch = global_batch;
  s.accumulate = accumulate;
  s.world = group.world();
  s.rank = group.rank();
  if (accumulate < 1)
    throw UsageError(who + ": --accumulate must be at least 1, not " + std::to_string(accumulate));
  if (global_batch % s.shards() != 0 || global_batch < s.shards())
    throw UsageError(who + ": a batch of " + std::to_string(global_batch) + " does not split into " +
                     std::to_string(s.shards()) + " equal micro-batches (" + std::to_string(s.world) +
                     " processes x --accumulate " + std::to_string(accumulate) + ")");
  s.micro_batch = global_batch / s.shards();
  return s;
}

}  // namespace dojo::train
