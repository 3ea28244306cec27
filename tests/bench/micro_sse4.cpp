// Micro-benchmarks for sse4 (W = 4): see micro_kernels.h.
#include <benchmark/benchmark.h>
#include <immintrin.h>

#include <cstdint>

#include "kdrt/trace.h"
#include "packet.h"
#include "ray_prep.h"

#pragma GCC push_options
#pragma GCC target("sse4.2,popcnt")
#include "micro_kernels.h"

namespace kdrt::bench {
namespace {

void traversal_step_sse4(benchmark::State& state) { bench_traversal_step<4>(state, Isa::kSse4); }
void leaf_test_sse4(benchmark::State& state) { bench_leaf_test<4>(state, Isa::kSse4); }

}  // namespace
}  // namespace kdrt::bench
#pragma GCC pop_options

BENCHMARK(kdrt::bench::traversal_step_sse4);
BENCHMARK(kdrt::bench::leaf_test_sse4);
