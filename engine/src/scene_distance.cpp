// Scene distance queries: a near-first walk of the top level that skips every cell and instance
// whose box is farther than the best answer so far, each instance answering in object space
// through the mesh's closest_point (kdrt/distance.h).

#include <algorithm>
#include <array>
#include <cmath>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "kdrt/distance.h"
#include "kdrt/scene.h"
#include "scene_internal.h"

namespace kdrt {
namespace {

using detail::InstanceData;
using detail::SceneData;

const SurfaceIndex& no_surface() {
    static const SurfaceIndex index;
    return index;
}

/// Squared distance from p to box, in double (0 inside).
double box_d2(const Aabb& box, const double p[3]) noexcept {
    double d2 = 0.0;
    for (int a = 0; a < 3; ++a) {
        const double lo = box.lo[a], hi = box.hi[a];
        const double e = p[a] < lo ? lo - p[a] : (p[a] > hi ? p[a] - hi : 0.0);
        d2 += e * e;
    }
    return d2;
}

/// The answer of instance `geom` (the arithmetic of closest_point's contract). `tris` non-null:
/// the brute-force oracle instead of the tree search.
SceneClosestPoint instance_closest(const Scene& scene, uint32_t geom, Vec3 p,
                                   const DistanceOptions& options,
                                   const std::vector<TriVerts>* tris) noexcept {
    const SceneData& s = scene.data();
    const InstanceData& in = s.inst[geom];
    const SceneInstance& inst = s.instances[geom];
    const double scale = *in.scale;
    const double q[3] = {static_cast<double>(p.x) - in.trans[0],
                         static_cast<double>(p.y) - in.trans[1],
                         static_cast<double>(p.z) - in.trans[2]};
    Vec3 obj;
    for (int i = 0; i < 3; ++i)
        obj[i] = static_cast<float>(in.inv[3 * i] * q[0] + in.inv[3 * i + 1] * q[1] +
                                    in.inv[3 * i + 2] * q[2]);
    DistanceOptions o = options;
    o.max_distance = static_cast<float>(static_cast<double>(options.max_distance) / scale);
    const SurfaceIndex& index = inst.surface ? *inst.surface : no_surface();
    ClosestPoint c = tris ? brute_force_closest_point(*tris, index, obj, o)
                          : closest_point(*inst.tree, index, obj, o);
    if (!c.found()) return {};
    const auto world = static_cast<float>(scale * static_cast<double>(c.distance));
    if (!(world <= options.max_distance)) return {};
    const double cp[3] = {c.point.x, c.point.y, c.point.z};
    c.point = detail::to_world(in, cp);
    c.distance = world;
    return {c, geom};
}

void offer(SceneClosestPoint& best, const SceneClosestPoint& c) noexcept {
    if (!c.found()) return;
    if (!best.found() || c.closest.distance < best.closest.distance ||
        (c.closest.distance == best.closest.distance && c.geom < best.geom))
        best = c;
}

SceneClosestPoint search(const Scene& scene, Vec3 p, const DistanceOptions& options) noexcept {
    const SceneData& s = scene.data();
    SceneClosestPoint best;
    if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z) || s.refs.empty() ||
        !(options.max_distance >= 0.0f))
        return best;
    const double pd[3] = {p.x, p.y, p.z};
    // A computed world distance is at least the box distance less the similarity tolerance
    // (relative, 1e-5 in L^T L: under 1e-4 in distance) and the rounding of the object point
    // (the traversal margin's bound): boxes are skipped only beyond both.
    const double mag = std::max({std::fabs(pd[0]), std::fabs(pd[1]), std::fabs(pd[2])});
    const double slack = detail::kMarginScale * s.kappa_max * (3.0 * mag + 3.0 * s.size_max);
    const auto too_far = [&](double d2) {
        const double bound = best.found() ? best.closest.distance : options.max_distance;
        return std::sqrt(d2) * (1.0 - 1e-4) - slack > bound;
    };
    struct Entry {
        uint32_t node;
        Aabb cell;
    };
    std::array<Entry, detail::kTopMaxDepth + 2> stack;
    int size = 0;
    if (too_far(box_d2(s.bounds, pd))) return best;
    stack[size++] = {0, s.bounds};
    while (size > 0) {
        const Entry e = stack[--size];
        if (too_far(box_d2(e.cell, pd))) continue;
        uint32_t index = e.node;
        Aabb cell = e.cell;
        detail::TopNode node = s.nodes[index];
        while (!node.is_leaf()) {
            const int axis = node.axis();
            const float split = node.split();
            Aabb low = cell, high = cell;
            low.hi[axis] = split;
            high.lo[axis] = split;
            const bool near_low = p[axis] < split;
            const Aabb& far_cell = near_low ? high : low;
            if (!too_far(box_d2(far_cell, pd)))
                stack[size++] = {node.first_child() + (near_low ? 1u : 0u), far_cell};
            index = node.first_child() + (near_low ? 0u : 1u);
            cell = near_low ? low : high;
            node = s.nodes[index];
        }
        const uint32_t end = node.first_ref() + node.count();
        for (uint32_t r = node.first_ref(); r < end; ++r) {
            const uint32_t geom = s.refs[r];
            if (too_far(box_d2(s.inst[geom].world, pd))) continue;
            if (best.geom == geom) continue;  // answered already (referenced by another leaf)
            offer(best, instance_closest(scene, geom, p, options, nullptr));
        }
    }
    return best;
}

}  // namespace

void check_distance_query(const Scene& scene, bool sign) {
    const SceneData& s = scene.data();
    if (const auto g = s.first_not_similar) {
        throw SceneError(*g, "transform",
                         "scene instance " + std::to_string(*g) +
                             " transform is not a similarity (a rotation or mirror times a "
                             "uniform scale, plus a translation): distance queries need one");
    }
    if (const auto g = s.first_without_surface; sign && g) {
        throw SceneError(*g, "surface",
                         "scene instance " + std::to_string(*g) +
                             " has no surface index: signed distance needs one");
    }
}

SceneClosestPoint closest_point(const Scene& scene, Vec3 p, const DistanceOptions& options) {
    check_distance_query(scene, options.sign);
    return search(scene, p, options);
}

void closest_points(const Scene& scene, std::span<const Vec3> points,
                    std::span<SceneClosestPoint> out, const DistanceOptions& options) {
    check_distance_query(scene, options.sign);
    tbb::parallel_for(tbb::blocked_range<size_t>(0, points.size(), 64),
                      [&](const tbb::blocked_range<size_t>& range) {
                          for (size_t i = range.begin(); i != range.end(); ++i)
                              out[i] = search(scene, points[i], options);
                      });
}

SceneClosestPoint SceneOracle::closest_point(Vec3 p, const DistanceOptions& options) const {
    check_distance_query(scene_, options.sign);
    SceneClosestPoint best;
    if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) return best;
    for (uint32_t g = 0; g < scene_.size(); ++g) {
        if (scene_.world_bounds(g).empty()) continue;
        offer(best, instance_closest(scene_, g, p, options, tris_[g].get()));
    }
    return best;
}

}  // namespace kdrt
