#pragma once
// Internal: pieces shared by the SAH and middle-split builders.

#include <cstdint>
#include <span>
#include <vector>

#include "kdrt/kdtree.h"

namespace kdrt::detail {

/// A tree under construction, in the final layout: nodes[0] is this subtree's root, the two
/// children of every inner node are adjacent, pairs laid out depth-first. Child and ref indices
/// are local to the subtree until it is spliced into its parent.
struct SubTree {
    std::vector<KdNode> nodes{KdNode{}};
    std::vector<uint32_t> refs;
    uint32_t max_depth = 0;
};

/// Reserves the two adjacent child slots of inner node `slot` and returns the first one.
inline uint32_t add_child_pair(SubTree& tree, uint32_t slot, int axis, float split) {
    const auto first = static_cast<uint32_t>(tree.nodes.size());
    tree.nodes.emplace_back();
    tree.nodes.emplace_back();
    tree.nodes[slot] = KdNode::inner(axis, split, first);
    return first;
}

/// Writes a leaf for `prims` into `slot`.
inline void make_leaf(SubTree& tree, uint32_t slot, const std::vector<uint32_t>& prims) {
    tree.nodes[slot] =
        KdNode::leaf(static_cast<uint32_t>(prims.size()), static_cast<uint32_t>(tree.refs.size()));
    tree.refs.insert(tree.refs.end(), prims.begin(), prims.end());
}

/// Copies `child` (built separately, e.g. on another thread) into `tree` as the subtree rooted at
/// `slot`, rebasing its child and ref indices.
inline void splice(SubTree& tree, uint32_t slot, const SubTree& child) {
    const auto node_base = static_cast<uint32_t>(tree.nodes.size());
    const auto ref_base = static_cast<uint32_t>(tree.refs.size());
    auto rebase = [&](KdNode n) {
        // Local child index i >= 1 lands at node_base + i - 1 (the child's root goes to `slot`).
        return n.is_leaf() ? KdNode::leaf(n.prim_count(), n.first_ref() + ref_base)
                           : KdNode::inner(n.axis(), n.split(), n.first_child() + node_base - 1);
    };
    tree.nodes[slot] = rebase(child.nodes[0]);
    tree.nodes.reserve(tree.nodes.size() + child.nodes.size() - 1);
    for (size_t i = 1; i < child.nodes.size(); ++i) tree.nodes.push_back(rebase(child.nodes[i]));
    tree.refs.insert(tree.refs.end(), child.refs.begin(), child.refs.end());
    tree.max_depth = tree.max_depth > child.max_depth ? tree.max_depth : child.max_depth;
}

/// Fills tree.tris from the mesh, collapsing degenerate (zero-area) triangles to a point so that
/// no ray/triangle test can ever report them. Returns, per triangle, whether it is degenerate.
std::vector<uint8_t> prepare_triangles(const Mesh& mesh, std::vector<TriVerts>& tris);

/// Root cell: the bounds of the non-degenerate triangles, padded by a small relative margin so
/// that ray clipping is robust and flat meshes get a cell with volume.
Aabb root_cell(const std::vector<TriVerts>& tris, const std::vector<uint8_t>& degenerate);

/// Fills tree.leaf_refs with `refs` (mesh triangle ids, leaf after leaf) rewritten as indices into
/// tree.tris, and tree.tris, tri_ids and tri_slots with every triangle of `by_id` in leaf order:
/// numbered by first reference, then the unreferenced ones by id. The numbering is one serial
/// pass; the triangles are gathered in parallel chunks into an array that is not zero-filled.
void order_triangles(KdTree& tree, std::span<const uint32_t> refs,
                     const std::vector<TriVerts>& by_id);

/// Moves a finished SubTree into `tree` (its nodes in cache lines, the triangles `by_id` in leaf
/// order) and fills the statistics (build_ms excluded).
void finish_tree(KdTree& tree, SubTree&& sub, const std::vector<TriVerts>& by_id);

}  // namespace kdrt::detail
