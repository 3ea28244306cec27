#pragma once
// Internal: pieces shared by the SAH and middle-split builders.

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include "kdrt/kdtree.h"

namespace kdrt::detail {

/// While one of these lives (on any thread), the huge-page mappings of freed tree arrays
/// (free_tree_memory) are kept, and allocate_tree_memory serves big arrays from them (the
/// smallest kept range that holds the array; the rest of it stays kept) before it maps fresh
/// memory. When the last one ends, what is still kept is unmapped. A build holds one, so the
/// tree's final arrays take the pages its scratch arrays (the binned levels' arena) were given
/// and touched, instead of fresh pages to fault in. Kept memory is not zeroed.
///
/// The kept memory is capped: at most the sum of the live objects' `limit`s (whole 2 MiB pages;
/// what does not fit is unmapped at its free, and when one ends, what the others' limits do not
/// cover is unmapped). A build passes its own size, so a tree freed elsewhere while it runs (a
/// cache's eviction) is kept only up to what this build can use, not whole and outside the
/// caller's memory budget for as long as builds overlap.
class RecycleTreeMappings {
public:
    explicit RecycleTreeMappings(size_t limit);
    ~RecycleTreeMappings();
    RecycleTreeMappings(const RecycleTreeMappings&) = delete;
    RecycleTreeMappings& operator=(const RecycleTreeMappings&) = delete;

private:
    size_t limit_;
};

/// A kept mapping (RecycleTreeMappings) for an array of `bytes` (2 MiB or more), as
/// allocate_tree_memory would give it, or null where none is kept: never fresh memory. Freed by
/// free_tree_memory(p, bytes).
[[nodiscard]] void* take_kept_tree_memory(size_t bytes);

/// Bytes of mappings kept for reuse now (RecycleTreeMappings).
[[nodiscard]] size_t recycled_tree_bytes();

/// A tree under construction, in the final layout: nodes[0] is this subtree's root, the two
/// children of every inner node are adjacent, pairs laid out depth-first. Child and ref indices
/// are local to the subtree until it is spliced into its parent.
///
/// A subtree built on another thread can be handed over by defer_splice instead of splice: it is
/// kept whole in `deferred` and stands for the nodes and references splice would have appended
/// at that point, copied into place once (finish_tree writes the whole tree into arrays of its
/// final size in parallel, one copy per node; flatten_deferred does it in place). splice copied a
/// subtree once per level above it, the top levels' copies on one thread after both halves were
/// built. Writing to a tree with deferred subtrees (add_child_pair, make_leaf, splice) flattens
/// them first, so the result is always what splice gives.
struct SubTree {
    /// A subtree spliced in after `nodes` / `refs` (and the deferred ones before it): its root
    /// goes to `slot`, the rest of its `node_count` nodes and its `ref_count` references follow.
    struct Deferred {
        uint32_t slot = 0;
        size_t node_count = 0;
        size_t ref_count = 0;
        std::unique_ptr<SubTree> tree;
    };
    std::vector<KdNode> nodes{KdNode{}};
    std::vector<uint32_t> refs;
    uint32_t max_depth = 0;
    std::vector<Deferred> deferred;

    /// Nodes and references with the deferred subtrees spliced in.
    [[nodiscard]] size_t node_count() const noexcept {
        size_t n = nodes.size();
        for (const Deferred& d : deferred) n += d.node_count - 1;
        return n;
    }
    [[nodiscard]] size_t ref_count() const noexcept {
        size_t n = refs.size();
        for (const Deferred& d : deferred) n += d.ref_count;
        return n;
    }
};

/// Copies the deferred subtrees of `tree` into its own arrays, with splice's indices, and drops
/// them: afterwards `nodes` and `refs` are what splicing each at its defer_splice would have made.
/// `parallel`: the subtrees are copied by oneTBB tasks (only where no per-thread scratch is in use
/// by the caller: a builder's own writes flatten serially).
void flatten_deferred(SubTree& tree, bool parallel);

/// Reserves the two adjacent child slots of inner node `slot` and returns the first one.
inline uint32_t add_child_pair(SubTree& tree, uint32_t slot, int axis, float split) {
    if (!tree.deferred.empty()) flatten_deferred(tree, false);
    const auto first = static_cast<uint32_t>(tree.nodes.size());
    tree.nodes.emplace_back();
    tree.nodes.emplace_back();
    tree.nodes[slot] = KdNode::inner(axis, split, first);
    return first;
}

/// Writes a leaf for `prims` into `slot`.
inline void make_leaf(SubTree& tree, uint32_t slot, const std::vector<uint32_t>& prims) {
    if (!tree.deferred.empty()) flatten_deferred(tree, false);
    tree.nodes[slot] =
        KdNode::leaf(static_cast<uint32_t>(prims.size()), static_cast<uint32_t>(tree.refs.size()));
    tree.refs.insert(tree.refs.end(), prims.begin(), prims.end());
}

/// Copies `child` (built separately, e.g. on another thread) into `tree` as the subtree rooted at
/// `slot`, rebasing its child and ref indices.
void splice(SubTree& tree, uint32_t slot, SubTree& child);

/// What splice(tree, slot, child) gives once `tree` is flattened (flatten_deferred), without
/// copying `child` now: it is moved into tree.deferred.
void defer_splice(SubTree& tree, uint32_t slot, SubTree&& child);

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
/// that ray clipping is robust and flat meshes get a cell with volume. `tight`, if given, gets
/// those bounds unpadded.
Aabb root_cell(std::span<const TriVerts> tris, const std::vector<uint8_t>& degenerate,
               Aabb* tight = nullptr);

/// Makes `refs` (mesh triangle ids, leaf after leaf) tree.leaf_refs, each rewritten in place as an
/// index into tree.tris, and fills tree.tris, tri_ids and tri_slots with every triangle of `mesh`
/// in leaf order: numbered by first reference, then the unreferenced ones by id. The numbering is
/// one serial pass; the triangles (mesh_triangle, `degenerate` per id) are written in parallel
/// chunks into `buffer`, which becomes tree.tris: any array of the mesh's triangle count (its
/// contents are overwritten, never read). The build passes the triangles by id it no longer needs,
/// so tree.tris takes memory that is already mapped instead of a fresh array to fault in.
void order_triangles(KdTree& tree, TreeArray<uint32_t>&& refs, const Mesh& mesh,
                     std::span<const uint8_t> degenerate, TreeArray<TriVerts>&& buffer);

/// Moves a finished SubTree into `tree` (its nodes in cache lines, the triangles in leaf order:
/// order_triangles, into `buffer`) and fills the statistics (build_ms excluded).
void finish_tree(KdTree& tree, SubTree&& sub, const Mesh& mesh, std::span<const uint8_t> degenerate,
                 TreeArray<TriVerts>&& buffer);

}  // namespace kdrt::detail
