#pragma once
// Micro-benchmark bodies over the packet width W: one traversal step and one leaf (triangle)
// test. Included by micro_{sse4,avx2,avx512}.cpp after their `#pragma GCC target`, like the
// engine's kernels, so each is compiled for its own instruction set.

#include "micro_fixture.h"
#include "packet_kernel.h"

namespace kdrt::bench {
namespace {

template <int W>
void bench_traversal_step(benchmark::State& state, Isa isa) {
    if (!isa_supported(isa)) {
        state.SkipWithError("instruction set not supported by this CPU");
        return;
    }
    const MicroFixture& f = micro_fixture();
    uint16_t index[16];
    for (int l = 0; l < 16; ++l) index[l] = static_cast<uint16_t>(l);
    detail::Packet<W> pk;
    detail::setup_packet<W>(f.tree, f.rays.data(), index, W, pk);
    const KdNode node = f.tree.nodes[f.inner_node];
    detail::VF<W> tmin = pk.tmin, tmax = pk.tmax;
    uint32_t visited = 0;
    for ([[maybe_unused]] auto _ : state) {
        // The body of the packet kernel's inner loop: plane distances, widened intervals, masks.
        benchmark::DoNotOptimize(tmin);
        benchmark::DoNotOptimize(tmax);
        const int axis = node.axis();
        const detail::VF<W> t_split = (node.split() - pk.org[axis]) * pk.inv[axis];
        const detail::VF<W> near_max = t_split + pk.eps[axis], far_min = t_split - pk.eps[axis];
        const detail::VM<W> active = tmin <= tmax;
        const detail::VM<W> need_near = active & ~(near_max < tmin);
        const detail::VM<W> need_far = active & ~(far_min > tmax);
        // Not const: Google Benchmark 1.8 deprecates DoNotOptimize of a const value.
        detail::VF<W> new_tmax = simd::min<W>(near_max, tmax);
        visited += simd::bits<W>(need_near) + simd::bits<W>(need_far);
        benchmark::DoNotOptimize(new_tmax);
    }
    benchmark::DoNotOptimize(visited);
    state.SetItemsProcessed(state.iterations() * W);  // ray-steps
}

template <int W>
void bench_leaf_test(benchmark::State& state, Isa isa) {
    if (!isa_supported(isa)) {
        state.SkipWithError("instruction set not supported by this CPU");
        return;
    }
    const MicroFixture& f = micro_fixture();
    uint16_t index[16];
    for (int l = 0; l < 16; ++l) index[l] = static_cast<uint16_t>(l);
    detail::Packet<W> pk;
    detail::setup_packet<W>(f.tree, f.rays.data(), index, W, pk);
    const TriVerts& tri = f.tree.triangle(f.triangle);
    const detail::VM<W> active = pk.tmin <= pk.tmax;
    uint32_t hits = 0;
    for ([[maybe_unused]] auto _ : state) {
        detail::VF<W> t = simd::broadcast<W>(0.0f), u = t, v = t;
        benchmark::DoNotOptimize(pk);
        const detail::VM<W> hit = detail::intersect_triangle_packet<W>(pk, tri, active, t, u, v);
        hits += simd::bits<W>(hit);
        benchmark::DoNotOptimize(t);
    }
    benchmark::DoNotOptimize(hits);
    state.SetItemsProcessed(state.iterations() * W);  // ray-triangle tests
}

}  // namespace
}  // namespace kdrt::bench
