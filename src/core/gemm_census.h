// The matrix products a piece of work runs, counted as it runs them and timed again alone: the
// roofline of that work on this machine. A step's own shapes (512x256 by 256x1024, batched 64x64
// attention products, transposed operands in the backward pass) multiply at a different rate
// than the 1024^3 product `dojo bench` times, so "fraction of the roofline" is only meaningful
// against the products the step itself runs (docs/benchmarks.md, "The CPU roofline").
#pragma once

#include <c10/core/Device.h>
#include <c10/core/ScalarType.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace dojo {

// One product as an operator ran it: `batch` products of [m, k] x [k, n]; an operand is
// "transposed" when it was a transposed view (column-major), which BLAS reads differently.
struct GemmShape {
  int64_t batch = 1, m = 0, k = 0, n = 0;
  bool a_transposed = false, b_transposed = false;
  c10::ScalarType dtype = c10::ScalarType::Float;
  c10::Device device = c10::kCPU;

  double flops() const { return 2.0 * static_cast<double>(batch * m) * static_cast<double>(k * n); }
  bool operator<(const GemmShape& other) const;
  bool operator==(const GemmShape& other) const;
};

struct GemmRecord {
  GemmShape shape;
  int64_t calls = 0;
  double seconds_in_place = 0;  // summed over calls, timed inside the work
};

// While it lives, records every float matrix product (aten::mm, addmm, bmm, baddbmm) that the
// thread which made it runs, and the autograd threads running that thread's backward passes,
// with its time in place. One census at a time, destroyed on the thread that made it. Recording
// asks libtorch for every operator's inputs, which slows the work: time the work without a census
// and count its products with one.
class GemmCensus {
 public:
  GemmCensus();
  ~GemmCensus();
  GemmCensus(const GemmCensus&) = delete;
  GemmCensus& operator=(const GemmCensus&) = delete;

  // The products so far, one record per distinct shape, largest total FLOPs first.
  std::vector<GemmRecord> records() const;

  struct State;  // opaque; public only so that libtorch's callbacks can reach it

 private:
  std::unique_ptr<State> state_;
};

struct GemmRoofline {
  int64_t calls = 0;
  double flops = 0;                        // per pass of the work
  double seconds_in_place = 0;             // the products' time inside the work
  double seconds_alone = 0;                // the same products back to back, operands already in place
  std::vector<double> seconds_alone_each;  // per record, in the order given

  double gflops_alone() const { return seconds_alone > 0 ? flops / seconds_alone / 1e9 : 0; }
  // The share of `work_seconds` the products would take at their own speed: 1 means the work is
  // nothing but its products, each running as fast as it does alone.
  double fraction_of(double work_seconds) const {
    return work_seconds > 0 ? seconds_alone / work_seconds : 0;
  }
  // Totals and the fraction; with `records` (those timed), also the first `shapes` of them.
  nlohmann::json to_json(double work_seconds, const std::vector<GemmRecord>& records = {},
                         size_t shapes = 0) const;
};

// Times each recorded shape alone on its device (random operands in its layout and dtype,
// `repeats` rounds after one untimed one; the fastest round counts) and sums over the calls of
// one pass of the work.
GemmRoofline time_alone(const std::vector<GemmRecord>& records, int repeats);

// One line for a log: the products, their time alone and the work's fraction of it.
std::string describe(const GemmRoofline& roofline, double work_seconds);

}  // namespace dojo
