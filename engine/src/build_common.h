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

/// The triangle with mesh id `i` as the builders and the tree store it: its three corners, or, for
/// a degenerate (zero-area) one, its first corner three times, so that no ray/triangle test can
/// ever report it (every edge function is then exactly zero, so the watertight test rejects it for
/// any ray, in the tree and in the brute-force oracle alike).
inline TriVerts mesh_triangle(const Mesh& mesh, size_t i, bool degenerate) noexcept {
    const Vec3 v0 = mesh.corner(i, 0);
    const Vec3 v1 = degenerate ? v0 : mesh.corner(i, 1), v2 = degenerate ? v0 : mesh.corner(i, 2);
    return TriVerts{{v0.x, v0.y, v0.z}, {v1.x, v1.y, v1.z}, {v2.x, v2.y, v2.z}};
}

/// Fills `tris` with mesh_triangle of every triangle of the mesh, by id (sized without a
/// zero-fill, each element first touched by the parallel chunk that writes it). Returns, per
/// triangle, whether it is degenerate.
std::vector<uint8_t> prepare_triangles(const Mesh& mesh, TreeArray<TriVerts>& tris);

/// Root cell: the bounds of the non-degenerate triangles, padded by a small relative margin so
/// that ray clipping is robust and flat meshes get a cell with volume.
Aabb root_cell(std::span<const TriVerts> tris, const std::vector<uint8_t>& degenerate);

/// Fills tree.leaf_refs with `refs` (mesh triangle ids, leaf after leaf) rewritten as indices into
/// tree.tris, and tree.tris, tri_ids and tri_slots with every triangle of `mesh` in leaf order:
/// numbered by first reference, then the unreferenced ones by id. The numbering is one serial
/// pass; the triangles (mesh_triangle, `degenerate` per id) are written in parallel chunks into
/// `buffer`, which becomes tree.tris: any array of the mesh's triangle count (its contents are
/// overwritten, never read). The build passes the triangles by id it no longer needs, so tree.tris
/// takes memory that is already mapped instead of a fresh array to fault in.
void order_triangles(KdTree& tree, std::span<const uint32_t> refs, const Mesh& mesh,
                     std::span<const uint8_t> degenerate, TreeArray<TriVerts>&& buffer);

/// Moves a finished SubTree into `tree` (its nodes in cache lines, the triangles in leaf order:
/// order_triangles, into `buffer`) and fills the statistics (build_ms excluded).
void finish_tree(KdTree& tree, SubTree&& sub, const Mesh& mesh, std::span<const uint8_t> degenerate,
                 TreeArray<TriVerts>&& buffer);

}  // namespace kdrt::detail
