#pragma once
/// The kD-tree: compact 8-byte nodes, its builders, and its statistics.

#include <bit>
#include <cstddef>
#include <cstdint>
#include <iterator>
#include <new>
#include <span>
#include <type_traits>
#include <vector>

#include "kdrt/mesh.h"
#include "kdrt/tree_stats.h"
#include "kdrt/types.h"
#include "kdrt/uninitialized.h"

namespace kdrt {

/// Hard cap on tree depth. The builders never exceed it, so a traversal stack of
/// kMaxDepth + 1 entries cannot overflow.
inline constexpr int kMaxDepth = 64;

/// An 8-byte kD-tree node (Stoll 2005, "compact 8-byte nodes").
///
///   word0 bits 0..1   : 0,1,2 = inner node split axis (x,y,z); 3 = leaf
///   word0 bits 2..31  : inner: index of the first child (the second is first + 1)
///                       leaf : number of triangle references
///   word1             : inner: split position (IEEE f32 bits)
///                       leaf : index of the first reference in KdTree::leaf_refs
///
/// The two children of an inner node are adjacent; no node stores a bounding box.
class KdNode {
public:
    static constexpr uint32_t kLeafTag = 3;
    static constexpr uint32_t kMaxField = (1u << 30) - 1;

    [[nodiscard]] static constexpr KdNode inner(int axis, float split,
                                                uint32_t first_child) noexcept {
        return KdNode((first_child << 2) | static_cast<uint32_t>(axis),
                      std::bit_cast<uint32_t>(split));
    }
    [[nodiscard]] static constexpr KdNode leaf(uint32_t prim_count, uint32_t first_ref) noexcept {
        return KdNode((prim_count << 2) | kLeafTag, first_ref);
    }
    constexpr KdNode() noexcept = default;

    [[nodiscard]] constexpr bool is_leaf() const noexcept { return (word0_ & 3u) == kLeafTag; }
    [[nodiscard]] constexpr int axis() const noexcept { return static_cast<int>(word0_ & 3u); }
    [[nodiscard]] constexpr uint32_t first_child() const noexcept { return word0_ >> 2; }
    [[nodiscard]] constexpr float split() const noexcept { return std::bit_cast<float>(word1_); }
    [[nodiscard]] constexpr uint32_t prim_count() const noexcept { return word0_ >> 2; }
    [[nodiscard]] constexpr uint32_t first_ref() const noexcept { return word1_; }
    [[nodiscard]] constexpr uint32_t word0() const noexcept { return word0_; }
    [[nodiscard]] constexpr uint32_t word1() const noexcept { return word1_; }
    [[nodiscard]] static constexpr KdNode from_words(uint32_t w0, uint32_t w1) noexcept {
        return KdNode(w0, w1);
    }
    friend constexpr bool operator==(const KdNode&, const KdNode&) = default;

private:
    constexpr KdNode(uint32_t w0, uint32_t w1) noexcept : word0_(w0), word1_(w1) {}
    uint32_t word0_ = kLeafTag;  // an empty leaf
    uint32_t word1_ = 0;
};
static_assert(sizeof(KdNode) == 8);
static_assert(kMaxTriangles < (1u << 31), "a reference leaves bit 31 free (KdTree::kLastRef)");

/// A wide node: a complete 3-level treelet of the binary tree (7 split planes, 8 child slots) in
/// one 64-byte line, so a single ray makes three levels of decisions per dependent load
/// (issue 23). Derived from the binary nodes after a build or a load (make_wide_nodes).
///
///   bytes  0..27 : split[0..6], f32. Plane 0 is the treelet root; plane 1 + b0 its child on side
///                  b0 (0 = low, 1 = high); plane 3 + 2 b0 + b1 the grandchild on sides b0, b1.
///   bytes 28..31 : axes, u32: bits 2j..2j+1 hold plane j's axis (0 x, 1 y, 2 z); bits 14..31
///                  are 0. (A lane's code is one variable shift away, and picks the ray's
///                  origin, reciprocal and tolerance on that axis with one permute each.)
///   bytes 32..63 : slot[0..7], u32: the child on sides (b0, b1, b2), slot index 4 b0 + 2 b1 + b2.
///                  bits 0..1: kSlotNone (padding, never visited), kSlotEmpty (an empty leaf),
///                  kSlotLeaf, kSlotNode; bits 2..31: kSlotLeaf: the leaf's first reference in
///                  KdTree::leaf_refs (its run ends at the reference marked kLastRef), so a ray
///                  goes from the wide node straight to the leaf's references; kSlotNode: the
///                  child's index in KdTree::wide_nodes; kSlotEmpty: the empty leaf's index in
///                  KdTree::nodes.
///
/// A binary leaf above the third level is padded down: its subtree's missing planes split at
/// +inf on x, so every ray keeps its interval on the low side, where the leaf sits (slot with
/// b = 0 below it); the other slots are kSlotNone.
struct alignas(64) WideNode {
    static constexpr uint32_t kSlotNone = 0;
    static constexpr uint32_t kSlotEmpty = 1;
    static constexpr uint32_t kSlotLeaf = 2;
    static constexpr uint32_t kSlotNode = 3;
    static constexpr int kPlanes = 7;
    static constexpr int kSlots = 8;

    float split[kPlanes];
    uint32_t axes;
    uint32_t slot[kSlots];

    [[nodiscard]] static constexpr uint32_t make_slot(uint32_t tag, uint32_t index) noexcept {
        return (index << 2) | tag;
    }
    [[nodiscard]] constexpr int axis(int plane) const noexcept {
        return static_cast<int>((axes >> (2 * plane)) & 3u);
    }
    [[nodiscard]] static constexpr uint32_t slot_tag(uint32_t s) noexcept { return s & 3u; }
    [[nodiscard]] static constexpr uint32_t slot_index(uint32_t s) noexcept { return s >> 2; }
};
static_assert(sizeof(WideNode) == 64 && alignof(WideNode) == 64);
static_assert(offsetof(WideNode, axes) == 28 && offsetof(WideNode, slot) == 32);

/// Pre-processed triangle for the watertight intersection test: its three vertices, copied from
/// the mesh so traversal never touches the cold mesh arrays. 36 bytes.
struct TriVerts {
    float v0[3];
    float v1[3];
    float v2[3];
};
static_assert(sizeof(TriVerts) == 36);

/// Nodes per 64-byte cache line. A tree's nodes are laid out in lines (the builders cluster
/// them: each line holds a child pair and the pairs below it), and the node array starts on a
/// line boundary, so a descent stays within a line for two or three steps.
inline constexpr size_t kNodesPerLine = 64 / sizeof(KdNode);

/// Memory for a tree's arrays (tree_memory.cpp): 64-byte aligned, and an array of 2 MiB or more
/// is 2 MiB aligned and asks the kernel for transparent huge pages (madvise), so random accesses
/// over a big scene's tree miss the TLB far less often. Throws std::bad_alloc.
[[nodiscard]] void* allocate_tree_memory(size_t bytes);
void free_tree_memory(void* p, size_t bytes) noexcept;

/// The allocator of a tree's arrays (allocate_tree_memory).
template <class T>
struct TreeAllocator {
    using value_type = T;
    TreeAllocator() noexcept = default;
    template <class U>
    TreeAllocator(const TreeAllocator<U>&) noexcept {}  // NOLINT(google-explicit-constructor)
    [[nodiscard]] T* allocate(size_t n) {
        return static_cast<T*>(allocate_tree_memory(n * sizeof(T)));
    }
    void deallocate(T* p, size_t n) noexcept { free_tree_memory(p, n * sizeof(T)); }
    /// Default-initialises (for the trivial types this is allowed for: leaves unwritten).
    template <class U>
    void construct(U* p, Uninitialized /*tag*/) noexcept {
        static_assert(std::is_trivially_default_constructible_v<U>);
        ::new (static_cast<void*>(p)) U;
    }
    friend bool operator==(const TreeAllocator&, const TreeAllocator&) noexcept { return true; }
};

/// One of a tree's arrays.
template <class T>
using TreeArray = std::vector<T, TreeAllocator<T>>;

/// A tree array of `n` uninitialised elements (see Uninitialized): every element must be written
/// before it is read.
template <class T>
[[nodiscard]] TreeArray<T> uninitialized_tree_array(size_t n) {
    return TreeArray<T>(detail::UninitializedTags{0}, detail::UninitializedTags{n});
}

/// The node array: starts on a cache line.
using NodeArray = TreeArray<KdNode>;

enum class Builder : uint32_t {
    kSah = 0,     ///< cost-optimised: Wald & Havran 2006 O(N log N) event sweep, perfect splits
    kMiddle = 1,  ///< the "hack" tree: middle of the largest extent, fixed leaf size and depth
};

/// Build settings. The SAH costs are relative: only their ratio and the bonus matter. The
/// default C_isect/C_trav = 0.3 makes a traversal step the dearer operation, as it is here: a
/// step is a dependent load, while a leaf's triangles are tested back to back (for a whole packet
/// at once). tests/bench/README.md lists the measurements that chose it.
struct BuildOptions {
    Builder builder = Builder::kSah;
    float traversal_cost = 1.0f;     ///< C_trav: cost of one traversal step
    float intersection_cost = 0.3f;  ///< C_isect: cost of one ray/triangle test
    float empty_bonus = 0.1f;       ///< cost of a split with an empty side is scaled by (1 - bonus)
    int max_depth = kMaxDepth;      ///< safety net only (clamped to [0, kMaxDepth])
    uint32_t middle_leaf_size = 8;  ///< kMiddle: stop at this many triangles
    int middle_max_depth = 24;      ///< kMiddle: stop at this depth
    friend bool operator==(const BuildOptions&, const BuildOptions&) = default;
};

/// An immutable, self-contained acceleration structure: traversal reads only these arrays.
/// Thread-safe for concurrent queries.
struct KdTree {
    Aabb bounds;      ///< root cell (mesh bounds, padded slightly)
    NodeArray nodes;  ///< nodes[0] is the root; in cache lines, children after their parent
    /// The same tree as 3-level treelets (the single-ray kernel's): wide_nodes[0] holds the top
    /// three levels; empty when the root is a leaf. Derived from `nodes` (make_wide_nodes).
    TreeArray<WideNode> wide_nodes;
    /// Marks the last reference of each leaf's run in leaf_refs (bit 31: a tris index is below
    /// kMaxTriangles), so a kernel that starts at a leaf's first reference needs no count.
    static constexpr uint32_t kLastRef = 1u << 31;
    /// The leaves' references: indices into tris (kLastRef masked off), each leaf one run
    /// [first_ref, first_ref + prim_count), no two runs overlapping, the last of each marked.
    TreeArray<uint32_t> leaf_refs;
    /// Every triangle of the mesh, in leaf order: the order of first reference in leaf_refs, then
    /// the triangles no leaf references (degenerate ones) by id. A leaf's triangles are mostly
    /// neighbours in memory, so a ray's leaf tests touch few cache lines.
    TreeArray<TriVerts> tris;
    TreeArray<uint32_t> tri_ids;      ///< tris[i] is mesh triangle tri_ids[i]
    std::vector<uint32_t> tri_slots;  ///< mesh triangle id -> its index in tris (the inverse)

    /// The triangle with mesh id `id`.
    [[nodiscard]] const TriVerts& triangle(uint32_t id) const noexcept {
        return tris[tri_slots[id]];
    }
    BuildOptions options;
    TreeStats stats;
};

/// Builds a kD-tree over `mesh` with the builder and costs in `options`. Validates the mesh first
/// (throws MeshError). Uses the calling thread's oneTBB arena for parallelism; the result is
/// byte-identical at any thread count. Degenerate (zero-area) triangles are left out of the tree.
[[nodiscard]] KdTree build_kdtree(const Mesh& mesh, const BuildOptions& options = {});

/// The triangles of `tree` indexed by mesh triangle id (what make_tri_verts gives for its mesh):
/// the brute-force oracle's input.
[[nodiscard]] std::vector<TriVerts> triangles_by_id(const KdTree& tree);

/// Recomputes the structural statistics of `tree` (everything but build_ms, which it keeps).
[[nodiscard]] TreeStats compute_stats(const KdTree& tree);

/// The wide nodes of a tree whose binary `nodes` are given (root at 0, children adjacent):
/// KdTree::wide_nodes. Linear in the node count. Throws std::length_error when the tree has
/// 2^30 wide nodes or more, or a leaf's first reference is 2^30 or more.
[[nodiscard]] TreeArray<WideNode> make_wide_nodes(std::span<const KdNode> nodes);

/// Sets KdTree::kLastRef on the last reference of each non-empty leaf of `nodes` in `refs` (and
/// clears it elsewhere). The leaves' runs must lie inside `refs` and not overlap.
void mark_leaf_runs(std::span<const KdNode> nodes, std::span<uint32_t> refs) noexcept;

}  // namespace kdrt
