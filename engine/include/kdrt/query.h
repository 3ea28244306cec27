#pragma once
/// Queries beyond the closest hit: every hit along a ray.

#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/trace.h"
#include "kdrt/types.h"

namespace kdrt {

/// Largest max_hits the engine takes (callers such as the server set their own, lower limit).
inline constexpr uint32_t kMaxHitsPerRay = 1u << 20;

struct AllHitsOptions {
    /// At most this many hits are kept per ray: the nearest ones in (t, prim) order. 1 ..
    /// kMaxHitsPerRay (0 keeps none, only the counts).
    uint32_t max_hits = 64;
    /// Report a group of coincident hits (a ray through a shared edge or vertex hits every
    /// triangle there) once, so that counting hits counts surface crossings.
    /// A group is a run of consecutive hits (in (t, prim) order) each within a tolerance in t of
    /// the run's first and sharing a vertex (bitwise equal position) with an earlier member. The
    /// tolerance covers the rounding of the watertight test, which computes t per triangle: 64
    /// ulps of the largest coordinate of the ray origin and the run's first triangle, divided by
    /// the largest direction component. A group whose triangles all face one way along the ray (the
    /// sign of d . n, n the right-hand normal of v0 v1 v2) is one crossing and is reported once, as
    /// its member with the lowest prim. A group facing both ways is the ray touching the surface at
    /// a fold (a silhouette edge or vertex): it keeps two hits, the lowest prim facing each way, so
    /// the parity of the count is unchanged. On a closed, consistently oriented mesh the merged
    /// count of a ray from a point outside is even and from a point inside odd. (A fold exactly at
    /// a vertex where the surface also crosses the ray would be reported as a touch; such a group
    /// needs the ray through the vertex's rounded position and is not otherwise told apart.)
    bool merge_coincident = false;
    /// How the batch is traversed, as for closest hit (TraceOptions): packets of same-octant rays
    /// (every lane making its own single-ray cell decisions) or single rays; auto uses packets
    /// where they pay. Every mode and ISA gives the same answers, bit for bit.
    TraceMode mode = TraceMode::kAuto;
    std::optional<Isa> isa = std::nullopt;  ///< default: default_isa(); unsupported: falls back
};

/// Every hit of a batch of rays, in CSR form: the kept hits of ray i are
/// hits[offsets[i] .. offsets[i+1]), sorted by (t, prim); counts[i] is the number of all its hits
/// in [tmin, tmax] (after merging), which may exceed the number kept.
struct AllHits {
    std::vector<uint64_t> offsets;  ///< rays + 1 entries, offsets[0] = 0
    std::vector<Hit> hits;
    std::vector<uint32_t> counts;  ///< rays entries
};

/// Every hit of `ray` with tmin <= t <= tmax, each triangle once, sorted by (t, prim), with
/// `merge_coincident` applied when asked for. The triangle test is the closest-hit kernel's
/// (watertight, the same t, u, v bits), so the first entry equals intersect(tree, ray) when
/// nothing is merged. An invalid ray has none. `out` is replaced; returns out.size().
/// Thread-safe.
uint32_t intersect_all(const KdTree& tree, const Ray& ray, bool merge_coincident,
                       std::vector<Hit>& out);

/// The same for a batch, in parallel over the current oneTBB arena. The answer is the same at
/// any thread count. Throws std::bad_alloc.
[[nodiscard]] AllHits intersect_all(const KdTree& tree, std::span<const Ray> rays,
                                    const AllHitsOptions& options);

/// The number of hits of each ray (what AllHits::counts holds), without keeping the hits.
void count_intersections(const KdTree& tree, std::span<const Ray> rays, bool merge_coincident,
                         std::span<uint32_t> counts);
/// The same with the traversal of `options` (its max_hits is not used).
void count_intersections(const KdTree& tree, std::span<const Ray> rays,
                         const AllHitsOptions& options, std::span<uint32_t> counts);

/// The oracle: every hit by testing every triangle (`tris` indexed by mesh triangle id, as
/// triangles_by_id gives them), sorted and merged like intersect_all.
[[nodiscard]] std::vector<Hit> brute_force_intersect_all(std::span<const TriVerts> tris,
                                                         const Ray& ray, bool merge_coincident);

/// Unit geometric normal of `tri`: the right-hand normal of v0 v1 v2 (its winding, not turned
/// towards any ray), the cross product taken in double, then scaled and rounded to float. The
/// zero vector for a degenerate triangle (which is never hit).
[[nodiscard]] Vec3 triangle_normal(const TriVerts& tri) noexcept;

/// The world-space point of `hit` on `tri`: (1-u-v) v0 + u v1 + v v2 in float (on the triangle to
/// rounding, unlike o + t d, which is off by ulps of |t d|).
[[nodiscard]] Vec3 hit_point(const TriVerts& tri, const Hit& hit) noexcept;

/// triangle_normal and hit_point of each hit (of `tree`'s mesh), in parallel over the current
/// arena. Either output may be empty (not computed); otherwise it has hits.size() entries.
void hit_attributes(const KdTree& tree, std::span<const Hit> hits, std::span<Vec3> normals,
                    std::span<Vec3> points);

}  // namespace kdrt
