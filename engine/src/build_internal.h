#pragma once
// Internal: the builders behind build_kdtree.

#include <emmintrin.h>

#include <algorithm>
#include <array>
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
    /// What intersecting a leaf of `n` triangles costs, in triangle tests. Must not decrease
    /// with `n` (the exact sweep's pruning bounds rely on it).
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
    /// `empty_cuts_in_place`: a cut of empty space hands the node's event lists to its other
    /// child as they are (the same tree as copying them; false only for the tests that show it).
    /// `prune_sweep`: the sweep skips blocks of candidates that provably cost too much (the same
    /// tree; false only for the tests that show it).
    ExactSahBuilder(std::span<const TriVerts> tris, const BuildOptions& options,
                    bool empty_cuts_in_place = true, bool prune_sweep = true);
    ~ExactSahBuilder();
    ExactSahBuilder(const ExactSahBuilder&) = delete;
    ExactSahBuilder& operator=(const ExactSahBuilder&) = delete;

    /// Builds the subtree over `prims` into `slot` of `out` (appending its nodes and references,
    /// as splice would), its root at depth `depth`. Each box must be the triangle clipped to
    /// `cell` (clip_to_cell), and prims must be in increasing triangle order (the event sort
    /// relies on it), each triangle at most once. No other thread may use `out` meanwhile.
    void build(SubTree& out, uint32_t slot, const Aabb& cell, std::span<const PrimBox> prims,
               uint32_t depth);

    /// build() over every triangle of the builder's mesh that `skip` does not flag and whose
    /// vertex bounds meet `cell`, each box those bounds in `cell` (vertex_bounds_in_cell): the
    /// binned root's hand-over of the whole mesh, with no list of boxes made first. `count`:
    /// how many such triangles there are.
    void build_all(SubTree& out, uint32_t slot, const Aabb& cell, std::span<const uint8_t> skip,
                   size_t count, uint32_t depth);

private:
    template <typename EachPrim>
    void build_events(SubTree& out, uint32_t slot, const Aabb& cell, size_t count, uint32_t depth,
                      const EachPrim& each_prim);

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
/// Inline: the binned root computes it for every triangle in each of its passes.
inline bool vertex_bounds_in_cell(const TriVerts& tri, const Aabb& cell, Aabb& out) {
    for (int a = 0; a < 3; ++a) {
        const float lo = std::min({tri.v0[a], tri.v1[a], tri.v2[a]});
        const float hi = std::max({tri.v0[a], tri.v1[a], tri.v2[a]});
        out.lo[a] = std::max(lo, cell.lo[a]);
        out.hi[a] = std::min(hi, cell.hi[a]);
        if (out.lo[a] > out.hi[a]) return false;
    }
    return true;
}

/// Sorts the 64-bit integers [first, last) ascending, as std::sort does (the exact sweep's
/// events, the straddlers' new ones above all), with a partition step free of data-dependent
/// branches. No quadratic case (std::sort past a depth limit).
void sort_events(uint64_t* first, uint64_t* last) noexcept;

/// Where the binned top levels hand over to the exact sweep.
struct BinnedParams {
    /// Nodes with fewer references than this are built by the exact sweep (UINT32_MAX: the
    /// whole build is exact; 0: binned as long as the bins find a split that beats a leaf).
    uint32_t exact_below = 4096;
    uint32_t bins = 64;  ///< per axis, clamped to [4, 256]; small nodes use fewer
    /// The exact sweep hands a node's event lists to the non-empty child of a cut of empty space
    /// as they are, instead of classifying and copying them (ExactSahBuilder). The tree is the
    /// same either way; tests turn it off to compare.
    bool empty_cuts_in_place = true;
    /// The exact sweep skips blocks of candidates whose lower bound shows they cannot be chosen
    /// (ExactSahBuilder). The tree is the same either way; tests turn it off to compare.
    bool prune_sweep = true;
    /// The root is counted, bounded and binned straight from the triangles, and its list of
    /// references is made only where a binned split divides it (not where the exact sweep takes
    /// the whole mesh). The tree is the same either way; tests turn it off to compare.
    bool root_from_triangles = true;
};

/// Maps a coordinate to its bin on one axis: [lo, lo + count / scale] in `count` equal bins,
/// coordinates below and above in the end bins.
struct BinMap {
    double lo = 0, scale = 0;
    uint32_t count = 1;
    [[nodiscard]] uint32_t operator()(float x) const noexcept {
        const double f = (double{x} - lo) * scale;
        const auto b = f > 0 ? static_cast<uint32_t>(f) : 0u;
        return b < count ? b : count - 1;
    }
};

/// The binned levels' BinMap for a reference's six bounds at once, two per SSE2 operation (the
/// scalar maps took about a third of a binned level's instructions). The same double arithmetic
/// per coordinate, so the same bins bit for bit: clamping the bin coordinate to [0, count - 1]
/// before truncating it gives what truncating and then clamping gives (a NaN or a coordinate at
/// or below the range lands in bin 0) wherever the scalar conversion is defined (bin
/// coordinates below 2^32; the binned levels bin references within the range).
class BoundsBinMap {
public:
    /// Where the bins of lo[a] and hi[a] are in the answer.
    static constexpr int kLo[3] = {0, 1, 4};
    static constexpr int kHi[3] = {2, 3, 5};

    explicit BoundsBinMap(const std::array<BinMap, 3>& m) noexcept {
        // Lanes (low, high) of the three pairs: (x, y) of lo, (x, y) of hi, (z of lo, z of hi).
        constexpr int kAxis[3][2] = {{0, 1}, {0, 1}, {2, 2}};
        for (int k = 0; k < 3; ++k) {
            const BinMap& a = m[kAxis[k][0]];
            const BinMap& b = m[kAxis[k][1]];
            lo_[k] = _mm_set_pd(b.lo, a.lo);
            scale_[k] = _mm_set_pd(b.scale, a.scale);
            last_[k] = _mm_set_pd(b.count - 1.0, a.count - 1.0);
        }
    }
    void operator()(const std::array<float, 3>& lo, const std::array<float, 3>& hi,
                    std::array<uint32_t, 6>& bins) const noexcept {
        const __m128d zero = _mm_setzero_pd();
        auto pair = [&](int k, __m128 two) {
            __m128d t = _mm_mul_pd(_mm_sub_pd(_mm_cvtps_pd(two), lo_[k]), scale_[k]);
            t = _mm_min_pd(_mm_max_pd(t, zero), last_[k]);  // max(NaN, 0) is 0
            return _mm_cvttpd_epi32(t);
        };
        auto two = [](const float* p) {
            return _mm_castsi128_ps(_mm_loadl_epi64(reinterpret_cast<const __m128i*>(p)));
        };
        const __m128i bl = pair(0, two(lo.data()));
        const __m128i bh = pair(1, two(hi.data()));
        const __m128i bz = pair(2, _mm_unpacklo_ps(_mm_load_ss(&lo[2]), _mm_load_ss(&hi[2])));
        _mm_storeu_si128(reinterpret_cast<__m128i*>(bins.data()), _mm_unpacklo_epi64(bl, bh));
        _mm_storel_epi64(reinterpret_cast<__m128i*>(bins.data() + 4), bz);
    }

private:
    // NOLINTNEXTLINE(*-avoid-c-arrays): std::array<__m128d> drops the vector type's attributes
    __m128d lo_[3], scale_[3], last_[3];
};

/// SAH build with min-max binned splits (Shevtsov et al. 2007, all three axes in one pass,
/// parallel over references) on nodes of at least params.exact_below references, and the exact
/// sweep below. Deterministic: byte-identical output at any thread count. `root`: root_cell's
/// cell; `tight`: the bounds it pads (every triangle that is not degenerate lies in the cell).
void build_binned(std::span<const TriVerts> tris, const std::vector<uint8_t>& degenerate,
                  const Aabb& root, const Aabb& tight, const BuildOptions& options,
                  const BinnedParams& params, SubTree& out);

/// build_kdtree with explicit binning parameters (build_kdtree uses the defaults); tests use it to
/// force the binned or the exact phase.
[[nodiscard]] KdTree build_kdtree_with(const Mesh& mesh, const BuildOptions& options,
                                       const BinnedParams& params);

/// The "hack" tree: middle of the largest extent, fixed leaf size and depth. Baseline only.
void build_middle(std::span<const TriVerts> tris, const std::vector<uint8_t>& degenerate,
                  const Aabb& root, const BuildOptions& options, SubTree& out);

}  // namespace kdrt::detail
