#pragma once
/// HitClearance: per mesh tree, which single-return scene hits need no every-hit window.
///
/// A scene's single merged return (scan_lidar and scan_pinhole with one return, nearest_hits
/// with max_hits 1 and merging) takes the closest hit of an instance, then, to apply the merge
/// rule, traces that instance's every-hit window around it. Where the closest hit is provably
/// alone in its merged group the window would answer the closest hit itself; an instance that
/// carries its tree's HitClearance (SceneInstance::clearance) skips the window there. The
/// answers are the same with or without it, bit for bit: only the work differs.
///
/// Building one costs about 0.6 times its tree's build (once per tree: instances of one mesh
/// should share it); it holds 52 bytes a triangle (bytes(): about 0.74 times the tree's own
/// arrays). The engine keeps no copy: the caller owns it (the server's MeshCache keeps it with
/// the tree and counts it in its memory budget).
///
/// Thread safety: immutable after build_hit_clearance; read concurrently by any number of scans.

#include <cstdint>
#include <span>
#include <vector>

#include "kdrt/kdtree.h"

namespace kdrt {

namespace detail {
/// One triangle's edge planes: g * (n . p - c) for each edge, n the unit normal of the plane
/// through the edge perpendicular to the triangle, pointing inwards (computed in double, stored
/// rounded to float: off by less than 2^-21 M at the points it is asked about); and the largest
/// |coordinate| of the triangle (part of the merge tolerance's magnitude). engine/src/
/// scene_clearance.h and .cpp say what g is and why the test suffices. 52 bytes.
struct ClearanceRecord {
    float plane[3][4];
    float mag;
};
static_assert(sizeof(ClearanceRecord) == 52);
}  // namespace detail

class HitClearance {
public:
    HitClearance() = default;
    /// Triangles covered: the tree's triangle count (its tri_slots.size()).
    [[nodiscard]] size_t size() const noexcept { return tris_.size(); }
    /// Memory held (the records' allocation and the object).
    [[nodiscard]] uint64_t bytes() const noexcept {
        return sizeof(HitClearance) + tris_.capacity() * sizeof(detail::ClearanceRecord);
    }
    /// Internal: the records by mesh triangle id (the scene scan's test reads them).
    [[nodiscard]] std::span<const detail::ClearanceRecord> records() const noexcept {
        return tris_;
    }

private:
    friend HitClearance build_hit_clearance(const KdTree& tree);
    std::vector<detail::ClearanceRecord> tris_;
};

/// The clearance of `tree`'s triangles (in parallel over the calling thread's oneTBB arena).
/// Give it to every SceneInstance of this tree. Throws std::bad_alloc.
[[nodiscard]] HitClearance build_hit_clearance(const KdTree& tree);

}  // namespace kdrt
