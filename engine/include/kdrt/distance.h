#pragma once
/// Distance queries: the closest point on a mesh to each query point (within an optional maximum
/// distance), and signed distance / inside-outside on closed meshes.
///
/// Distances are to the mesh's non-degenerate triangles: a zero-area triangle (its edge cross
/// product exactly zero, the rule the tree builder uses) has no surface and is ignored, as rays
/// ignore it.
///
/// Exactness. Each triangle's closest point and squared distance are computed by one routine
/// (closest_on_triangle, in double); the answer is the triangle with the smallest squared
/// distance, an exact tie going to the lowest prim. The kD-tree search visits every cell that
/// could hold such a triangle, so it equals brute_force_closest_point bit for bit (tested).
///
/// The sign (Baerentzen & Aanaes 2005, "Signed distance computation using the angle weighted
/// pseudonormal"): p is inside when (p - q) . n < 0, q the closest point and n the pseudonormal of
/// the feature q lies on: the face normal for the interior of a triangle, the sum of the two face
/// normals for an edge, the angle-weighted sum of the face normals around a vertex. This is exact
/// on a closed, consistently oriented (edge-manifold) mesh, outside being where the right-hand
/// normals of v0 v1 v2 point. A point outside the mesh's bounding box is outside without that
/// test: however far it is, whatever its rounded closest feature, it is never inside. On any other
/// mesh (an edge with one triangle or more than two, or two triangles running along it the same
/// way) the side is Side::kUnknown. A point on the surface (distance 0) is outside. Vertices are
/// identified by position (bitwise equal coordinates), not by index, so a mesh whose triangles were
/// uploaded as a soup still counts as closed.

#include <atomic>
#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include "kdrt/distance_types.h"
#include "kdrt/kdtree.h"
#include "kdrt/types.h"

namespace kdrt {

/// What the sign needs of a mesh, built once per tree: the pseudonormals of every triangle's
/// face, edges and corners, and whether the mesh is closed and consistently oriented.
/// Immutable once built; thread-safe for concurrent queries.
struct SurfaceIndex {
    /// Per mesh triangle id, 7 unit vectors (x, y, z each): the face normal, the pseudonormals of
    /// edges 0-1, 1-2, 2-0, then of corners 0, 1, 2 (Feature order). Zero for a degenerate one.
    std::vector<float> pseudonormals;
    bool closed = false;             ///< every edge has two triangles, running along it oppositely
    uint32_t boundary_edges = 0;     ///< edges with one triangle
    uint32_t nonmanifold_edges = 0;  ///< edges with more than two
    uint32_t misoriented_edges = 0;  ///< edges with two triangles running along it the same way
    uint32_t degenerate_triangles = 0;
    Aabb bounds;  ///< of every triangle's corners (the interior of a closed mesh is inside it)
};

/// Builds the SurfaceIndex of `tree`'s mesh. O(N log N). Throws std::bad_alloc.
[[nodiscard]] SurfaceIndex build_surface_index(const KdTree& tree);

/// One triangle's closest point to p, in double. Feature::kNone (d2 = +inf) for a degenerate
/// triangle.
struct TriangleClosest {
    double d2 = std::numeric_limits<double>::infinity();  ///< squared distance
    double u = 0.0, v = 0.0;                              ///< weights of v1 and v2
    double point[3] = {0.0, 0.0, 0.0};
    Feature feature = Feature::kNone;
};
/// The closest point of `tri` to `p` (Voronoi regions of the vertices, edges and face, tested in
/// double; every input float is exact in double). noexcept; p must be finite.
[[nodiscard]] TriangleClosest closest_on_triangle(const TriVerts& tri, const double p[3]) noexcept;

struct DistanceOptions {
    /// Only triangles with squared distance <= max_distance^2 (in double) count; +inf: no limit.
    /// NaN or negative: nothing is found.
    float max_distance = std::numeric_limits<float>::infinity();
    /// Decide ClosestPoint::side (needs the index to be of a closed mesh; else kUnknown).
    bool sign = false;
};

/// The closest point of `tree`'s mesh to `p`: a best-first kD-tree search over the cells by their
/// box distance (the boxes from the root bounds and the split planes), which ends as soon as the
/// nearest waiting cell is farther than the best triangle so far. Its rounding slack is relative
/// to the best distance and to the mesh's coordinates, not to p's, so a point 10^6 mesh sizes
/// away costs about what a near one does; beyond about 10^13 the triangles' rounded distances tie
/// and every tying one is tested (DistanceControl::max_work bounds a batch of such points). A NaN
/// or infinite p finds nothing. `index` must be build_surface_index(tree) (read only when
/// options.sign). Thread-safe. Throws std::bad_alloc (the search's heap).
[[nodiscard]] ClosestPoint closest_point(const KdTree& tree, const SurfaceIndex& index, Vec3 p,
                                         const DistanceOptions& options);

/// Limits and cancellation of a batch of distance queries (the server's requests).
struct DistanceControl {
    /// Checked before each point; once seen true, the batch stops (DistanceStatus::kCancelled).
    /// The pointee must outlive the call. nullptr: never cancelled.
    const std::atomic<bool>* cancel = nullptr;
    /// Work units (cells visited plus triangles tested) the batch may use; when the total passes
    /// it, the batch stops (DistanceStatus::kOverWork). 0: no limit.
    uint64_t max_work = 0;
    /// Called from worker threads, one call at a time, about every 2^16 work units of the batch
    /// (a millisecond or so of one thread), e.g. to set *cancel when the client has gone. Must
    /// not throw.
    std::function<void()> poll;
};

enum class DistanceStatus : int {
    kDone = 0,       ///< every answer was written
    kCancelled = 1,  ///< DistanceControl::cancel was set: the answers are incomplete
    kOverWork = 2,   ///< DistanceControl::max_work was exceeded: the answers are incomplete
};

/// What a batch did.
struct DistanceStats {
    uint64_t work = 0;  ///< cells visited plus triangles tested, over the points searched
    DistanceStatus status = DistanceStatus::kDone;
};

/// The same for a batch (out.size() == points.size()), in parallel over the current oneTBB
/// arena, in tasks of a few points; the same answers at any thread count. Stops early, leaving
/// some answers unwritten, when `control` says so (the status tells). Throws std::bad_alloc.
DistanceStats closest_points(const KdTree& tree, const SurfaceIndex& index,
                             std::span<const Vec3> points, std::span<ClosestPoint> out,
                             const DistanceOptions& options, const DistanceControl& control = {});

/// The oracle: the closest point by testing every triangle (`tris` indexed by mesh triangle id, as
/// triangles_by_id gives them), with the same tie rule and sign.
[[nodiscard]] ClosestPoint brute_force_closest_point(std::span<const TriVerts> tris,
                                                     const SurfaceIndex& index, Vec3 p,
                                                     const DistanceOptions& options) noexcept;

}  // namespace kdrt
