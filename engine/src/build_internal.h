#pragma once
// Internal: the two builders behind build_kdtree.

#include <cstdint>
#include <vector>

#include "build_common.h"
#include "kdrt/kdtree.h"

namespace kdrt::detail {

/// Wald & Havran 2006 SAH build over the non-degenerate triangles into `out`.
void build_sah(const std::vector<TriVerts>& tris, const std::vector<uint8_t>& degenerate,
               const Aabb& root, const BuildOptions& options, SubTree& out);

/// The "hack" tree: middle of the largest extent, fixed leaf size and depth. Baseline only.
void build_middle(const std::vector<TriVerts>& tris, const std::vector<uint8_t>& degenerate,
                  const Aabb& root, const BuildOptions& options, SubTree& out);

}  // namespace kdrt::detail
