#include "core/gemm_census.h"

#include <ATen/record_function.h>
#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <sstream>
#include <tuple>

#include "core/error.h"

namespace dojo {
namespace {

using Clock = std::chrono::steady_clock;

auto key(const GemmShape& s) {
  return std::make_tuple(s.batch, s.m, s.k, s.n, s.a_transposed, s.b_transposed, s.dtype,
                         static_cast<int>(s.device.type()), static_cast<int>(s.device.index()));
}

// A column-major view (a transposed contiguous matrix): BLAS reads it as "T".
bool is_transposed(const at::Tensor& t) {
  const int64_t d = t.dim();
  return !t.is_contiguous() && t.stride(d - 2) == 1 && t.stride(d - 1) == t.size(d - 2);
}

// The product an operator is about to run, if it is one we count: its two matrix operands.
bool gemm_of(const at::RecordFunction& fn, GemmShape& shape) {
  const std::string name = fn.name();
  int first = -1;
  if (name == "aten::mm" || name == "aten::bmm") first = 0;
  if (name == "aten::addmm" || name == "aten::baddbmm") first = 1;
  if (first < 0) return false;
  const auto inputs = fn.inputs();
  if (static_cast<int>(inputs.size()) < first + 2 || !inputs[first].isTensor() ||
      !inputs[first + 1].isTensor())
    return false;
  const auto& a = inputs[first].toTensor();
  const auto& b = inputs[first + 1].toTensor();
  if (!a.is_floating_point() || a.dim() < 2 || a.dim() != b.dim()) return false;
  shape.batch = a.dim() == 3 ? a.size(0) : 1;
  shape.m = a.size(-2);
  shape.k = a.size(-1);
  shape.n = b.size(-1);
  shape.a_transposed = is_transposed(a);
  shape.b_transposed = is_transposed(b);
  shape.dtype = a.scalar_type();
  shape.device = a.device();
  return true;
}

struct Nested : at::ObserverContext {};

struct InFlight : at::ObserverContext {
  GemmShape shape;
  Clock::time_point start;
};

}  // namespace

bool GemmShape::operator<(const GemmShape& other) const { return key(*this) < key(other); }
bool GemmShape::operator==(const GemmShape& other) const { return key(*this) == key(other); }

struct GemmCensus::State {
  std::map<GemmShape, GemmRecord> records;
  at::CallbackHandle handle = 0;
};

namespace {

// The census recording now, and the lock that every record and the census's end take: a product
// finishing on an autograd thread never writes into a census being destroyed.
std::mutex& census_mutex() {
  static std::mutex mutex;
  return mutex;
}

GemmCensus::State*& active_census() {
  static GemmCensus::State* state = nullptr;
  return state;
}

// Products nested in a counted product (an operator built on another) are not counted twice.
thread_local int gemm_depth = 0;

}  // namespace

GemmCensus::GemmCensus() : state_(std::make_unique<State>()) {
  {
    std::lock_guard<std::mutex> lock(census_mutex());
    DOJO_CHECK(active_census() == nullptr, "gemm census: another census is recording");
    active_census() = state_.get();
  }
  auto start = [](const at::RecordFunction& fn) -> std::unique_ptr<at::ObserverContext> {
    GemmShape shape;
    if (!gemm_of(fn, shape)) return nullptr;
    if (gemm_depth++ > 0) return std::make_unique<Nested>();  // nested: the end only unwinds
    auto ctx = std::make_unique<InFlight>();
    ctx->shape = shape;
    ctx->start = Clock::now();
    return ctx;
  };
  auto end = [](const at::RecordFunction&, at::ObserverContext* ctx) {
    if (ctx == nullptr) return;
    --gemm_depth;
    auto* in_flight = dynamic_cast<InFlight*>(ctx);
    if (in_flight == nullptr) return;
    const double seconds = std::chrono::duration<double>(Clock::now() - in_flight->start).count();
    std::lock_guard<std::mutex> lock(census_mutex());
    State* state = active_census();
    if (state == nullptr) return;
    auto& record = state->records[in_flight->shape];
    record.shape = in_flight->shape;
    record.calls += 1;
    record.seconds_in_place += seconds;
  };
  // Thread-local: libtorch hands it to the autograd threads that run this thread's backward
  // passes, not to unrelated threads (data loaders) whose products are not the work's.
  state_->handle = at::addThreadLocalCallback(
      at::RecordFunctionCallback(start, end).needsInputs(true).scopes({at::RecordScope::FUNCTION}));
}

GemmCensus::~GemmCensus() {
  at::removeCallback(state_->handle);
  std::lock_guard<std::mutex> lock(census_mutex());
  active_census() = nullptr;
}

std::vector<GemmRecord> GemmCensus::records() const {
  std::vector<GemmRecord> out;
  {
    std::lock_guard<std::mutex> lock(census_mutex());
    for (const auto& [shape, record] : state_->records) out.push_back(record);
  }
  std::sort(out.begin(), out.end(), [](const GemmRecord& a, const GemmRecord& b) {
    return a.shape.flops() * static_cast<double>(a.calls) > b.shape.flops() * static_cast<double>(b.calls);
  });
  return out;
}

nlohmann::json GemmRoofline::to_json(double work_seconds, const std::vector<GemmRecord>& records,
                                     size_t shapes) const {
  nlohmann::json j = {{"calls", calls},
                      {"gflop", flops / 1e9},
                      {"ms_in_place", 1e3 * seconds_in_place},
                      {"ms_alone", 1e3 * seconds_alone},
                      {"gflops_alone", gflops_alone()},
                      {"fraction_of_roofline", fraction_of(work_seconds)}};
  for (size_t i = 0; i < std::min({shapes, records.size(), seconds_alone_each.size()}); ++i) {
    const auto& r = records[i];
    j["shapes"].push_back({{"batch", r.shape.batch},
                           {"mkn", {r.shape.m, r.shape.k, r.shape.n}},
                           {"transposed", {r.shape.a_transposed, r.shape.b_transposed}},
                           {"dtype", c10::toString(r.shape.dtype)},
                           {"device", r.shape.device.str()},
                           {"calls", r.calls},
                           {"ms_in_place", 1e3 * r.seconds_in_place},
                           {"ms_alone", 1e3 * seconds_alone_each[i]}});
  }
  return j;
}

GemmRoofline time_alone(const std::vector<GemmRecord>& records, int repeats) {
  DOJO_CHECK(repeats >= 1, "gemm census: at least one timed round");
  torch::NoGradGuard no_grad;
  auto operand = [&](const GemmShape& s, int64_t rows, int64_t cols, bool transposed) {
    const auto options = torch::TensorOptions().device(s.device).dtype(s.dtype);
    const int64_t batch = s.batch;
    auto t = transposed ? torch::randn({batch, cols, rows}, options).transpose(1, 2)
                        : torch::randn({batch, rows, cols}, options);  // [batch, rows, cols]
    return batch == 1 ? t.squeeze(0) : t;
  };
  auto sync = [](const c10::Device& device) {
    if (device.is_cuda()) torch::cuda::synchronize();
  };
  GemmRoofline roofline;
  for (const auto& r : records) {
    const auto& s = r.shape;
    const auto a = operand(s, s.m, s.k, s.a_transposed);
    const auto b = operand(s, s.k, s.n, s.b_transposed);
    double best = 0;
    for (int round = 0; round <= repeats; ++round) {  // round 0 untimed
      sync(s.device);
      const auto start = Clock::now();
      for (int64_t call = 0; call < r.calls; ++call)
        (void)(s.batch == 1 ? torch::mm(a, b) : torch::bmm(a, b));
      sync(s.device);
      const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
      if (round == 1 || (round > 1 && seconds < best)) best = seconds;
    }
    roofline.calls += r.calls;
    roofline.flops += s.flops() * static_cast<double>(r.calls);
    roofline.seconds_in_place += r.seconds_in_place;
    roofline.seconds_alone += best;
    roofline.seconds_alone_each.push_back(best);
  }
  return roofline;
}

std::string describe(const GemmRoofline& r, double work_seconds) {
  std::ostringstream line;
  line.precision(3);
  line << r.calls << " matrix products a step (" << r.flops / 1e9 << " GFLOP) take " << 1e3 * r.seconds_alone
       << " ms alone (" << r.gflops_alone() << " GFLOP/s, the step's roofline); the step ("
       << 1e3 * work_seconds << " ms) runs at " << 100 * r.fraction_of(work_seconds) << " % of it";
  return line.str();
}

}  // namespace dojo
