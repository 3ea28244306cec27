#pragma once
// Internal: the builders behind build_kdtree.

#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include "build_common.h"
#include "kdrt/kdtree.h"

namespace kdrt::detail {

/// A triangle of a node under construction and its bounds within the node's cell.
struct PrimBox {
    Aabb box;
    uint32_t prim = 0;
};

/// The surface area heuristic, as both SAH builders (binned and exact) evaluate it, in one place:
/// a change to the cost of a leaf (e.g. counting SIMD blocks instead of triangles) is made here
/// and reaches every candidate of both phases. Costs are in units of BuildOptions' C_trav and
/// C_isect; probabilities are a child's surface area over its parent's.
struct SahCost {
    double c_trav = 1.0;
    double c_isect = 0.3;
    double empty_scale = 0.9;  ///< 1 - empty_bonus

    [[nodiscard]] static SahCost from(const BuildOptions& options) noexcept {
        return {double{options.traversal_cost}, double{options.intersection_cost},
                1.0 - double{options.empty_bonus}};
    }
    /// What intersecting a leaf of `n` triangles costs, in triangle tests.
    [[nodiscard]] static double tests(uint32_t n) noexcept { return static_cast<double>(n); }
    /// Cost of making a node of `n` triangles a leaf.
    [[nodiscard]] double leaf(uint32_t n) const noexcept { return c_isect * tests(n); }
    /// True when no split of a node of `n` triangles can cost less than making it a leaf: every
    /// split costs c_trav plus a non-negative term, and c_trav is already at least the leaf's
    /// cost (with the defaults, n <= 3). The builder then needs no candidate planes at all.
    [[nodiscard]] bool leaf_always_cheaper(uint32_t n) const noexcept {
        return c_isect >= 0 && empty_scale >= 0 && leaf(n) <= c_trav;
    }
    /// Cost of splitting a node into children reached with probabilities `pl`, `pr` holding
    /// `nl`, `nr` triangles. A split with an empty side earns the empty bonus.
    [[nodiscard]] double split(double pl, double pr, uint32_t nl, uint32_t nr) const noexcept {
        double cost = c_isect * (pl * tests(nl) + pr * tests(nr));
        if (nl == 0 || nr == 0) cost *= empty_scale;
        return cost + c_trav;
    }
};

/// The exact SAH builder (Wald & Havran 2006, build_sah.cpp), callable on any cell: the whole
/// mesh, or a node the binned top levels (build_binned.cpp) hand down. One instance serves a whole
/// build (its per-thread scratch is sized by the triangle count); build() may be called
/// concurrently from oneTBB tasks of the same arena.
class ExactSahBuilder {
public:
    ExactSahBuilder(const std::vector<TriVerts>& tris, const BuildOptions& options);
    ~ExactSahBuilder();
    ExactSahBuilder(const ExactSahBuilder&) = delete;
    ExactSahBuilder& operator=(const ExactSahBuilder&) = delete;

    /// Builds the subtree over `prims` into `slot` of `out` (appending its nodes and references,
    /// as splice would), its root at depth `depth`. Each box must be the triangle clipped to
    /// `cell` (clip_to_cell), and prims must be in increasing triangle order (the event sort
    /// relies on it), each triangle at most once. No other thread may use `out` meanwhile.
    void build(SubTree& out, uint32_t slot, const Aabb& cell, std::span<const PrimBox> prims,
               uint32_t depth);

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

/// Bounds of `tri` clipped to the closed box `cell` (Sutherland-Hodgman in double, rounded
/// outwards to float), or, where clipping leaves nothing (a triangle that only touches the cell
/// within rounding), its vertex bounds within the cell. False if even those do not overlap.
bool clip_to_cell(const TriVerts& tri, const Aabb& cell, Aabb& out);

/// clip_to_cell of `tri` in the two children of a split on `axis` (cells `left` and `right`,
/// equal on every other axis), computed together: bit for bit what two clip_to_cell calls give,
/// with the planes of the axes before `axis` clipped once. `*_ok` false: the triangle misses
/// that child.
void clip_to_children(const TriVerts& tri, const Aabb& left, const Aabb& right, int axis,
                      bool& left_ok, Aabb& left_box, bool& right_ok, Aabb& right_box);

/// True only if `tri` is clearly apart from `cell`: it misses the cell grown by a margin far
/// larger than rounding errors (a triangle that merely touches the cell is never reported).
bool misses_cell(const TriVerts& tri, const Aabb& cell);

/// What `!misses_cell(tri, cell) && clip_to_cell(tri, cell, out)` gives, with one clip where
/// the triangle's clipped polygon is not empty (it then reaches the cell, so it cannot miss the
/// cell grown by misses_cell's margin): the binned phase's cut references at the hand-over to
/// the exact sweep, which clipped each of them twice.
bool clip_unless_missing(const TriVerts& tri, const Aabb& cell, Aabb& out);

/// Bounds of the triangle's vertices intersected with `cell`; false if they do not overlap.
bool vertex_bounds_in_cell(const TriVerts& tri, const Aabb& cell, Aabb& out);

/// Where the binned top levels hand over to the exact sweep.
struct BinnedParams {
    /// Nodes with fewer references than this are built by the exact sweep (UINT32_MAX: the
    /// whole build is exact; 0: binned as long as the bins find a split that beats a leaf).
    uint32_t exact_below = 4096;
    uint32_t bins = 64;  ///< per axis, clamped to [4, 256]; small nodes use fewer
};

/// SAH build with min-max binned splits (Shevtsov et al. 2007, all three axes in one pass,
/// parallel over references) on nodes of at least params.exact_below references, and the exact
/// sweep below. Deterministic: byte-identical output at any thread count.
void build_binned(const std::vector<TriVerts>& tris, const std::vector<uint8_t>& degenerate,
                  const Aabb& root, const BuildOptions& options, const BinnedParams& params,
                  SubTree& out);

/// build_kdtree with explicit binning parameters (build_kdtree uses the defaults); tests use it to
/// force the binned or the exact phase.
[[nodiscard]] KdTree build_kdtree_with(const Mesh& mesh, const BuildOptions& options,
                                       const BinnedParams& params);

/// The "hack" tree: middle of the largest extent, fixed leaf size and depth. Baseline only.
void build_middle(const std::vector<TriVerts>& tris, const std::vector<uint8_t>& degenerate,
                  const Aabb& root, const BuildOptions& options, SubTree& out);

}  // namespace kdrt::detail
