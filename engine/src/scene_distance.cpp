// Scene distance queries: a near-first walk of the top level that skips every cell and instance
// whose box is farther than the best answer so far, each instance answering in object space
// through the mesh's nearest-triangle search (kdrt/distance.h), the work of both levels counted
// against the batch's DistanceControl.

#include <algorithm>
#include <array>
#include <cmath>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/partitioner.h>

#include "distance_internal.h"
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

/// The answer of instance `geom` (the arithmetic of closest_point's contract): the tree search
/// `search` (its work added to search->work), or with `tris` non-null the brute-force oracle.
SceneClosestPoint instance_closest(const Scene& scene, uint32_t geom, Vec3 p,
                                   const DistanceOptions& options, detail::NearestSearch* search,
                                   const std::vector<TriVerts>* tris) {
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
                          : search->run(*inst.tree, index, obj, o);
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

/// The closest point of the scene to `p`, into `best`. Its work (top-level cells visited, plus
/// for each instance searched 1 and its mesh search's work) is charged to `batch`, when there is
/// one, after each instance, and the batch is checked before each: false when it stopped
/// (cancelled or over its work) before the answer was complete.
bool search(const Scene& scene, Vec3 p, const DistanceOptions& options,
            detail::NearestSearch& mesh_search, detail::DistanceBatch* batch,
            SceneClosestPoint& best) {
    const SceneData& s = scene.data();
    best = {};
    if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z) || s.refs.empty() ||
        !(options.max_distance >= 0.0f))
        return true;
    uint64_t work = 0;  // not charged yet
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
    if (too_far(box_d2(s.bounds, pd))) return true;
    stack[size++] = {0, s.bounds};
    while (size > 0) {
        const Entry e = stack[--size];
        if (too_far(box_d2(e.cell, pd))) continue;
        ++work;
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
            ++work;
        }
        const uint32_t end = node.first_ref() + node.count();
        for (uint32_t r = node.first_ref(); r < end; ++r) {
            const uint32_t geom = s.refs[r];
            if (too_far(box_d2(s.inst[geom].world, pd))) continue;
            if (best.geom == geom) continue;  // answered already (referenced by another leaf)
            // A far point may search every instance, each testing every triangle: the batch is
            // checked per instance, not only per point.
            if (batch != nullptr && batch->stopped()) return false;
            mesh_search.work = 0;
            offer(best, instance_closest(scene, geom, p, options, &mesh_search, nullptr));
            work += 1 + mesh_search.work;
            if (batch != nullptr && !batch->charge(work)) return false;
            work = 0;
        }
    }
    return batch == nullptr || work == 0 || batch->charge(work);
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
    detail::NearestSearch mesh_search;
    SceneClosestPoint best;
    (void)search(scene, p, options, mesh_search, nullptr, best);
    return best;
}

DistanceStats closest_points(const Scene& scene, std::span<const Vec3> points,
                             std::span<SceneClosestPoint> out, const DistanceOptions& options,
                             const DistanceControl& control) {
    check_distance_query(scene, options.sign);
    detail::DistanceBatch batch(control);
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, points.size(), detail::kDistanceBlockPoints),
        [&](const tbb::blocked_range<size_t>& range) {
            detail::NearestSearch mesh_search;
            for (size_t i = range.begin(); i != range.end(); ++i) {
                if (batch.stopped()) return;
                if (!search(scene, points[i], options, mesh_search, &batch, out[i])) return;
            }
        },
        tbb::simple_partitioner());
    return batch.stats();
}

SceneClosestPoint SceneOracle::closest_point(Vec3 p, const DistanceOptions& options) const {
    check_distance_query(scene_, options.sign);
    SceneClosestPoint best;
    if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) return best;
    for (uint32_t g = 0; g < scene_.size(); ++g) {
        if (scene_.world_bounds(g).empty()) continue;
        offer(best, instance_closest(scene_, g, p, options, nullptr, tris_[g].get()));
    }
    return best;
}

}  // namespace kdrt
