// Micro-benchmarks for avx512 (W = 16): see micro_kernels.h.
#include <benchmark/benchmark.h>
#include <immintrin.h>

#include <cstdint>

#include "kdrt/trace.h"
#include "packet.h"
#include "ray_prep.h"

#pragma GCC push_options
#pragma GCC target("avx512f,avx512dq,avx512vl,avx512bw,popcnt")
#include "micro_kernels.h"

namespace kdrt::bench {
namespace {

void traversal_step_avx512(benchmark::State& state) {
    bench_traversal_step<16>(state, Isa::kAvx512);
}
void leaf_test_avx512(benchmark::State& state) { bench_leaf_test<16>(state, Isa::kAvx512); }

}  // namespace
}  // namespace kdrt::bench
#pragma GCC pop_options

BENCHMARK(kdrt::bench::traversal_step_avx512);
BENCHMARK(kdrt::bench::leaf_test_avx512);
