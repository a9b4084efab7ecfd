// The float32 multiply-add throughput of the metegs kernels' threads: the peak that the arithmetic floor of the
// raster benchmark assumes, measured on this machine, now, with the threads and the scheduling the kernels use.
//
// `chunks` jobs of `iterations` steps go to metegs::parallel_for, one chunk per claim (the kernels' dynamic
// scheduling: a thread that another process slows down runs fewer chunks). Each step is one multiply-add
// acc = acc * a + b on each of CHAINS independent 16-lane accumulators: enough chains to cover the multiply-add
// latency on every x86 core with one or two vector multiply-add units (4 cycles x 2 units = 8 in flight). With
// a = b = 1 every accumulator ends at `iterations` exactly (below 2^24), so the returned checksum is
// chunks x CHAINS x 16 x iterations: proof that all the counted work ran. a and b come from the caller, so the
// compiler cannot fold the chains away, and an empty volatile asm hides the accumulators' start from it: without
// it, GCC computed the chunk once for a thread's whole range (the chunks are the same pure computation) and merged
// identical chains, which timed a fraction of the counted work (8 chunks on one thread: 930 "GFLOP/s" on a core
// that peaks at about 115).

#include "metegs_cpu.h"

#include <torch/csrc/utils/pybind.h>  // pybind11 with at::Tensor's casters, without the whole C++ API

#include <chrono>

namespace metegs_cpu {
namespace {

constexpr int CHAINS = METEGS_AVX512 ? 12 : 6;  // independent chains that fill the vector registers

double run_chunk(int64_t iterations, Lanes16 a, Lanes16 b) {
  Lanes16 acc[CHAINS];
  for (auto& v : acc) v = Lanes16{};
  asm volatile("" : : "r"(acc) : "memory");  // opaque start: no chunk or chain is the same computation to GCC
  for (int64_t i = 0; i < iterations; ++i) {
#pragma GCC unroll 12
    for (int k = 0; k < CHAINS; ++k) acc[k] = fmadd16(acc[k], a, b);
  }
  double sum = 0;
  for (const auto& v : acc)
    for (int l = 0; l < 16; ++l) sum += v[l];
  return sum;
}

}  // namespace

std::vector<double> fma_throughput(int64_t chunks, int64_t iterations, double a, double b) {
  TORCH_CHECK(chunks > 0 && iterations > 0, "fma_throughput: chunks and iterations must be positive");
  const Lanes16 va = Lanes16{} + static_cast<float>(a), vb = Lanes16{} + static_cast<float>(b);
  std::vector<double> sums(chunks);
  const auto t0 = std::chrono::steady_clock::now();
  metegs::parallel_for(0, chunks, 1, [&](int64_t begin, int64_t end) {
    for (int64_t c = begin; c < end; ++c) sums[c] = run_chunk(iterations, va, vb);
  });
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  double checksum = 0;
  for (double s : sums) checksum += s;
  const double flops = 2.0 * 16.0 * CHAINS * static_cast<double>(iterations) * static_cast<double>(chunks);
  return {seconds, flops, checksum};
}

}  // namespace metegs_cpu

// An extension of its own, built only by the raster benchmark (`metegs.bench.peak`), never part of the kernels'.
PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  const auto nogil = py::call_guard<py::gil_scoped_release>();
  m.def("fma_throughput", &metegs_cpu::fma_throughput,
        "float32 multiply-adds on the kernels' threads -> [seconds, flops, checksum] (the machine's peak, measured)",
        nogil, py::arg("chunks"), py::arg("iterations"), py::arg("a") = 1.0, py::arg("b") = 1.0);
  m.attr("chains") = metegs_cpu::CHAINS;
  m.def("set_num_threads", [](int64_t n) { metegs::thread_override() = std::max<int64_t>(n, 0); },
        "threads of the probe called from this thread (0: torch's intra-op count)", py::arg("n"));
  m.def("get_num_threads", &metegs::num_threads, "threads the probe runs on when called from this thread");
}
