#pragma once
// Internal: the cache-line layout of a tree's nodes (see node_layout.cpp).

#include <span>

#include "kdrt/kdtree.h"

namespace kdrt::detail {

/// Lays out the nodes of a tree, given with the root at 0 and each inner node's children adjacent,
/// in cache lines of kNodesPerLine nodes: each line holds a child pair and, breadth first, the
/// child pairs below it, so a ray descending from the first pair of a line takes its next step
/// or two in the same line. Child indices are rewritten; leaves keep their references. Children
/// still come after their parents.
[[nodiscard]] NodeArray cluster_nodes(std::span<const KdNode> nodes);

}  // namespace kdrt::detail
