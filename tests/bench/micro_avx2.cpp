// Micro-benchmarks for avx2 (W = 8): see micro_kernels.h.
#include <benchmark/benchmark.h>
#include <immintrin.h>

#include <cstdint>

#include "kdrt/trace.h"
#include "packet.h"
#include "ray_prep.h"

#pragma GCC push_options
#pragma GCC target("avx2,popcnt")
#include "micro_kernels.h"

namespace kdrt::bench {
namespace {

void traversal_step_avx2(benchmark::State& state) { bench_traversal_step<8>(state, Isa::kAvx2); }
void leaf_test_avx2(benchmark::State& state) { bench_leaf_test<8>(state, Isa::kAvx2); }

}  // namespace
}  // namespace kdrt::bench
#pragma GCC pop_options

BENCHMARK(kdrt::bench::traversal_step_avx2);
BENCHMARK(kdrt::bench::leaf_test_avx2);
