#include "kdrt/trace.h"

#include <array>
#include <cmath>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "packet.h"
#include "ray_prep.h"

namespace kdrt {
namespace {

struct StackEntry {
    uint32_t node;
    float tmin;
    float tmax;
};

/// Closest hit so far. Initialised to (ray.tmax, kNoHit) so a hit at exactly tmax still counts.
struct Best {
    float t;
    uint32_t prim;
    float u, v;
};

/// The single-ray kernel (Stoll 2005): non-recursive, a fixed stack of (node, tmin, tmax), one
/// subtract and one multiply per step. With AnyHit it returns at the first hit; otherwise it keeps
/// the lexicographically smallest (t, prim) so ties do not depend on traversal order.
/// No counting: the public queries.
struct NoCount {
    void step() noexcept {}
    void leaf(uint32_t) noexcept {}
};
/// Counting into TraceCounters: kdrt-bench trace --stats.
struct Count {
    detail::TraceCounters& c;
    void step() noexcept { ++c.steps; }
    void leaf(uint32_t tris) noexcept {
        ++c.leaves;
        c.tri_tests += tris;
    }
};

template <bool AnyHit, class Counter>
bool traverse(const KdTree& tree, const Ray& ray, Best& best, Counter counter) noexcept {
    if (!detail::ray_is_valid(ray) || tree.bounds.empty()) return false;
    const detail::PreparedRay p = detail::prepare_ray(ray);
    float tmin = ray.tmin, tmax = ray.tmax;
    if (!detail::clip_to_box(p, tree.bounds, tmin, tmax)) return false;

    // Which child is near: the ray moves from the low to the high side when the reciprocal is
    // positive (+0 direction counts as positive, -0 as negative; see the NaN case below).
    const uint32_t near_is_high[3] = {std::signbit(p.inv_dir[0]) ? 1u : 0u,
                                      std::signbit(p.inv_dir[1]) ? 1u : 0u,
                                      std::signbit(p.inv_dir[2]) ? 1u : 0u};
    float eps[3];
    detail::traversal_eps(p, tree.bounds, eps);
    const KdNode* nodes = tree.nodes.data();
    const uint32_t* refs = tree.leaf_refs.data();
    const TriVerts* tris = tree.tris.data();
    const uint32_t* ids = tree.tri_ids.data();

    std::array<StackEntry, kMaxDepth + 2> stack;  // +1: the unconditional write past the top
    int stack_size = 0;
    uint32_t node_index = 0;
    bool found = false;
    for (;;) {
        KdNode node = nodes[node_index];
        while (!node.is_leaf()) {
            counter.step();
            const int axis = node.axis();
            const float t_split = (node.split() - p.org[axis]) * p.inv_dir[axis];
            const uint32_t near_child = node.first_child() + near_is_high[axis];
            const uint32_t far_child = node.first_child() + (near_is_high[axis] ^ 1u);
            // Each side's interval is widened by eps; a side is visited when its widened interval
            // meets [tmin, tmax]. The packet kernels make exactly these comparisons per lane, so
            // every path visits the same cells for a ray. Branch-free: the far child is always
            // written to the stack and kept only when both sides are needed. A ray lying in the
            // split plane (zero direction component, origin on the plane) has a NaN t_split: no
            // comparison holds, so it needs both sides with unchanged intervals, as it must
            // (triangles touching the plane may sit on either side).
            const float near_max = t_split + eps[axis], far_min = t_split - eps[axis];
            const bool need_near = !(near_max < tmin), need_far = !(far_min > tmax);
            const bool both = need_near && need_far;
            stack[stack_size] = {far_child, far_min > tmin ? far_min : tmin, tmax};
            stack_size += both ? 1 : 0;
            tmax = both && near_max < tmax ? near_max : tmax;
            node_index = need_near ? near_child : far_child;
            node = nodes[node_index];
        }
        counter.leaf(node.prim_count());
        const uint32_t end = node.first_ref() + node.prim_count();
        for (uint32_t r = node.first_ref(); r < end; ++r) {
            const uint32_t slot = refs[r];
            float t, u, v;
            if (!detail::intersect_triangle(p, tris[slot], ray.tmin, t, u, v)) continue;
            if constexpr (AnyHit) {
                if (t <= ray.tmax) return true;
            } else {
                const uint32_t prim = ids[slot];  // the tie rule and the answer use mesh ids
                if (t < best.t || (t == best.t && prim < best.prim)) {
                    best = {t, prim, u, v};
                    found = true;
                }
            }
        }
        // Cells come off the stack front to back; once one starts beyond the closest hit, so do
        // all the rest (a hit exactly at a cell's entry may still have a lower-id tie inside it).
        for (;;) {
            if (stack_size == 0) return found;
            const StackEntry& e = stack[--stack_size];
            if constexpr (!AnyHit) {
                if (e.tmin > best.t) return found;
            }
            node_index = e.node;
            tmin = e.tmin;
            tmax = e.tmax;
            break;
        }
    }
}

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

Hit to_hit(bool found, const Best& best) noexcept {
    return found ? Hit{best.t, best.prim, best.u, best.v} : Hit{};
}

constexpr size_t kSingleGrain = 1024;

}  // namespace

Hit intersect(const KdTree& tree, const Ray& ray) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    const bool found = traverse<false>(tree, ray, best, NoCount{});
    return to_hit(found, best);
}

bool occluded(const KdTree& tree, const Ray& ray) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    return traverse<true>(tree, ray, best, NoCount{});
}

namespace detail {

Hit intersect_counted(const KdTree& tree, const Ray& ray, TraceCounters& counters) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    const bool found = traverse<false>(tree, ray, best, Count{counters});
    return to_hit(found, best);
}

bool occluded_counted(const KdTree& tree, const Ray& ray, TraceCounters& counters) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    return traverse<true>(tree, ray, best, Count{counters});
}

}  // namespace detail

Hit brute_force_intersect(std::span<const TriVerts> tris, const Ray& ray) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    const bool found = brute_force<false>(tris, ray, best);
    return to_hit(found, best);
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
