#include "kdrt/trace.h"

#include <array>
#include <cmath>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "packet.h"
#include "ray_prep.h"
#include "wide_kernel.h"

namespace kdrt {
namespace {

using detail::Best;

template <bool AnyHit>
bool brute_force(std::span<const TriVerts> tris, const Ray& ray, Best& best) noexcept {
    if (!detail::ray_is_valid(ray)) return false;
    const detail::PreparedRay p = detail::prepare_ray(ray);
    bool found = false;
    for (uint32_t prim = 0; prim < tris.size(); ++prim) {
        float t, u, v;
        if (!detail::intersect_triangle(p, tris[prim], ray.tmin, t, u, v)) continue;
        if (t < best.t || (t == best.t && prim < best.prim)) {
            if constexpr (AnyHit) return true;
            best = {t, prim, u, v};
            found = true;
        }
    }
    return found;
}

constexpr size_t kSingleGrain = 1024;

}  // namespace

// The single-ray queries run on the default ISA's copy of the kernel (one indirect call); the
// baseline copy here (its 8-lane vectors in SSE2) serves CPUs without SSE4.1.
Hit intersect(const KdTree& tree, const Ray& ray) noexcept {
    if (const detail::PacketKernels* k = detail::single_ray_kernels())
        return k->single_intersect(tree, ray);
    return detail::wide_intersect(tree, ray);
}

bool occluded(const KdTree& tree, const Ray& ray) noexcept {
    if (const detail::PacketKernels* k = detail::single_ray_kernels())
        return k->single_occluded(tree, ray);
    return detail::wide_occluded(tree, ray);
}

namespace detail {

Hit intersect_counted(const KdTree& tree, const Ray& ray, TraceCounters& counters) noexcept {
    if (const PacketKernels* k = single_ray_kernels())
        return k->single_intersect_counted(tree, ray, counters);
    return wide_intersect_counted(tree, ray, counters);
}

bool occluded_counted(const KdTree& tree, const Ray& ray, TraceCounters& counters) noexcept {
    if (const PacketKernels* k = single_ray_kernels())
        return k->single_occluded_counted(tree, ray, counters);
    return wide_occluded_counted(tree, ray, counters);
}

}  // namespace detail

Hit brute_force_intersect(std::span<const TriVerts> tris, const Ray& ray) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    const bool found = brute_force<false>(tris, ray, best);
    return detail::to_hit(found, best);
}

bool brute_force_occluded(std::span<const TriVerts> tris, const Ray& ray) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    return brute_force<true>(tris, ray, best);
}

void intersect_single(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits) noexcept {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, rays.size(), kSingleGrain),
                      [&](const tbb::blocked_range<size_t>& range) {
                          for (size_t i = range.begin(); i != range.end(); ++i)
                              hits[i] = intersect(tree, rays[i]);
                      });
}

void occluded_single(const KdTree& tree, std::span<const Ray> rays,
                     std::span<uint8_t> occluded_out) noexcept {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, rays.size(), kSingleGrain),
                      [&](const tbb::blocked_range<size_t>& range) {
                          for (size_t i = range.begin(); i != range.end(); ++i)
                              occluded_out[i] = occluded(tree, rays[i]) ? 1 : 0;
                      });
}

}  // namespace kdrt
