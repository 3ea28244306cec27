#pragma once
/// Single-ray queries against a KdTree, and a brute-force reference.

#include <cstdint>
#include <span>

#include "kdrt/kdtree.h"
#include "kdrt/types.h"

namespace kdrt {

/// Closest hit of `ray` in `tree` with tmin <= t <= tmax. Among hits at exactly equal t the lowest
/// triangle id wins, so the answer does not depend on traversal order. Watertight (Woop, Benthin
/// & Wald 2013): a ray through a shared edge or vertex of a closed mesh always hits one triangle.
/// A ray with NaN/Inf components, a zero direction or tmin > tmax is a miss. Thread-safe.
[[nodiscard]] Hit intersect(const KdTree& tree, const Ray& ray) noexcept;

/// True when any triangle is hit with tmin <= t <= tmax. Stops at the first hit found.
[[nodiscard]] bool occluded(const KdTree& tree, const Ray& ray) noexcept;

/// The same answers as intersect/occluded, by testing every triangle: the oracle for tests.
[[nodiscard]] Hit brute_force_intersect(std::span<const TriVerts> tris, const Ray& ray) noexcept;
[[nodiscard]] bool brute_force_occluded(std::span<const TriVerts> tris, const Ray& ray) noexcept;

/// Pre-processed triangles of a mesh (what KdTree::tris holds), for brute_force_*. Degenerate
/// (zero-area) triangles are collapsed to a point, so no ray ever hits them.
[[nodiscard]] std::vector<TriVerts> make_tri_verts(const Mesh& mesh);

/// Batch queries for arbitrary input, over all threads of the current oneTBB arena. Answers come
/// back in input order; `hits` / `occluded_out` must have rays.size() elements (1 = occluded).
/// The engine picks the fastest kernel it has for the batch; every kernel gives the same answers.
void intersect(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits) noexcept;
void occluded(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded_out) noexcept;

/// The same, on the calling thread only (no tasks spawned): for callers that already run in
/// parallel over small blocks, such as the renderer's tiles.
void intersect_block(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits) noexcept;
void occluded_block(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded_out) noexcept;

/// Batch queries with the single-ray kernel only (the baseline that packets are measured against).
void intersect_single(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits) noexcept;
void occluded_single(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded_out) noexcept;

}  // namespace kdrt
