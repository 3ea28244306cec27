// kdrt-micro: Google Benchmark micro-benchmarks of one traversal step and one leaf test, for the
// scalar kernel and every packet width (micro_{sse4,avx2,avx512}.cpp). items_per_second is
// ray-steps or ray-triangle tests per second; widths the CPU lacks are reported as skipped.

#include <benchmark/benchmark.h>

#include <cmath>
#include <stdexcept>
#include <string>

#include "kdrt/camera.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/trace.h"
#include "micro_fixture.h"
#include "ray_prep.h"

namespace kdrt::bench {

const MicroFixture& micro_fixture() {
    static const MicroFixture fixture = [] {
        MicroFixture f;
        auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
        if (!mesh) throw std::runtime_error(mesh.error().to_string());
        f.tree = build_kdtree(*mesh);
        const Camera cam(default_camera(f.tree.bounds, 1.0f), 1024, 1024);
        for (int l = 0; l < 16; ++l)
            f.rays.push_back(cam.ray(504.5f + static_cast<float>(l), 512.5f));
        const Hit h = intersect(f.tree, f.rays[0]);
        f.triangle = h.is_hit() ? h.prim : 0;
        f.inner_node = 0;  // the root: every ray crosses it
        return f;
    }();
    return fixture;
}

namespace {

void traversal_step_scalar(benchmark::State& state) {
    const MicroFixture& f = micro_fixture();
    const detail::PreparedRay p = detail::prepare_ray(f.rays[0]);
    float eps[3];
    detail::traversal_eps(p, f.tree.bounds, eps);
    const KdNode node = f.tree.nodes[f.inner_node];
    float tmin = 0.0f, tmax = 100.0f;
    uint32_t visited = 0;
    for ([[maybe_unused]] auto _ : state) {
        benchmark::DoNotOptimize(tmin);
        benchmark::DoNotOptimize(tmax);
        const int axis = node.axis();
        const float t_split = (node.split() - p.org[axis]) * p.inv_dir[axis];
        const float near_max = t_split + eps[axis], far_min = t_split - eps[axis];
        visited += (far_min > tmax) ? 1u : (near_max < tmin ? 2u : 3u);
        // Not const: Google Benchmark 1.8 deprecates DoNotOptimize of a const value.
        float new_tmax = near_max < tmax ? near_max : tmax;
        benchmark::DoNotOptimize(new_tmax);
    }
    benchmark::DoNotOptimize(visited);
    state.SetItemsProcessed(state.iterations());
}

void leaf_test_scalar(benchmark::State& state) {
    const MicroFixture& f = micro_fixture();
    detail::PreparedRay p = detail::prepare_ray(f.rays[0]);  // not const: as new_tmax above
    const TriVerts& tri = f.tree.triangle(f.triangle);
    uint32_t hits = 0;
    for ([[maybe_unused]] auto _ : state) {
        float t = 0, u = 0, v = 0;
        benchmark::DoNotOptimize(p);
        hits += detail::intersect_triangle(p, tri, 0.0f, t, u, v) ? 1u : 0u;
        benchmark::DoNotOptimize(t);
    }
    benchmark::DoNotOptimize(hits);
    state.SetItemsProcessed(state.iterations());
}

}  // namespace
}  // namespace kdrt::bench

BENCHMARK(kdrt::bench::traversal_step_scalar);
BENCHMARK(kdrt::bench::leaf_test_scalar);
BENCHMARK_MAIN();
