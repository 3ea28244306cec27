// The top levels of the SAH build: min-max binned splits (Shevtsov, Soupikov and Kapustin 2007,
// "Highly parallel fast kd-tree construction for interactive ray tracing of dynamic scenes"),
// handing every node of fewer than BinnedParams::exact_below references to the exact sweep of
// build_sah.cpp.
//
// Why: the exact sweep keeps three sorted event lists per node and touches every event of every
// node, so the top levels, where a few nodes hold most of the events, cost O(N) event passes each
// and run on one or two threads. Binning needs one pass over the references per node (all three
// axes together, in parallel chunks) and O(bins) to evaluate the candidates.
//
// - A reference is a triangle and its bounds within the node's cell. Straddlers go to both
//   children with their bounds cut at the plane on the split axis only; they are clipped exactly
//   (Sutherland-Hodgman, as in the exact builder) once, when their node reaches the exact phase.
// - Candidates per axis: the bins-1 inner bin boundaries between the node's tight geometry
//   bounds, plus the two tight bounds themselves. The latter are the empty-space cuts (one side
//   holds nothing) that the exact sweep would also find; without them a big empty region would be
//   cut only at a bin boundary, leaving slivers of empty space in the non-empty child.
// - Counts at a boundary are min-max bin estimates (a reference's lower bound counts it on the
//   left, its upper bound on the right); the partition itself compares exactly, so the tree is
//   correct whatever the estimate. The cost formula is the exact sweep's (empty bonus included).
// - A node whose best binned split does not beat making it a leaf goes to the exact sweep, which
//   makes the final decision with perfect splits.
// Determinism: bins and bounds are integer sums and min/max over fixed-size chunks, combined in
// chunk order; the partition writes each chunk's references at offsets from a prefix sum. So the
// references keep their (triangle id) order and the tree is the same at any thread count.

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <memory>
#include <new>
#include <span>
#include <type_traits>
#include <utility>
#include <vector>

#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>

#include "build_arena.h"
#include "build_common.h"
#include "build_internal.h"
#include "geometry.h"

namespace kdrt::detail {
namespace {

/// A reference: a triangle id (bits 0..30) and its bounds within the node's cell. Bit 31 is set
/// when a binned split has cut the bounds (the triangle needs clipping before the exact phase).
/// Plain floats (no default member initialisers), so that the reference arrays below can be
/// allocated without writing them first.
struct Ref {
    std::array<float, 3> lo, hi;
    uint32_t prim_and_flag;

    [[nodiscard]] Aabb box() const noexcept {
        return {{lo[0], lo[1], lo[2]}, {hi[0], hi[1], hi[2]}};
    }
};
static_assert(std::is_trivially_default_constructible_v<Ref>);
constexpr uint32_t kCut = 0x80000000u;

/// A node's references: a range of the builder's arena (build_arena.h), given back to it once
/// the node is partitioned or handed to the exact sweep.
using RefArena = ArrayArena<Ref>;
using Refs = RefArena::Array;

/// Grows `b` to hold the reference's bounds.
inline void extend(Aabb& b, const Ref& r) noexcept {
    for (int a = 0; a < 3; ++a) {
        b.lo[a] = std::min(b.lo[a], r.lo[a]);
        b.hi[a] = std::max(b.hi[a], r.hi[a]);
    }
}
/// Grows `b` to hold `other`.
inline void extend(Aabb& b, const Aabb& other) noexcept {
    for (int a = 0; a < 3; ++a) {
        b.lo[a] = std::min(b.lo[a], other.lo[a]);
        b.hi[a] = std::max(b.hi[a], other.hi[a]);
    }
}

constexpr uint32_t kMaxBins = 256;
constexpr size_t kChunkRefs = size_t{1} << 13;     // references per parallel chunk
constexpr size_t kParallelRefs = size_t{1} << 15;  // nodes this big bin and partition in parallel
constexpr size_t kParallelSubtrees = 4096;         // ... and build their children concurrently
/// A binned split with at most 1/kNearlyEmpty of the node's references on one side is a cut of
/// (nearly) empty space. On the stadium (a small dense sphere inside a big box of 12 triangles)
/// the binned root took such a cut around the sphere where the exact sweep splits the sphere, and
/// shadow rays from the walls then tested 9.0 instead of 6.7 triangles each.
constexpr uint32_t kNearlyEmpty = 64;
/// Small nodes get fewer bins: one per kRefsPerBin references, at least kMinBins.
constexpr uint32_t kRefsPerBin = 8;
constexpr uint32_t kMinBins = 16;

struct BinnedSplit {
    bool valid = false;
    int axis = 0;
    float pos = 0;
    bool planar_left = false;  ///< where a reference lying in the plane goes
    bool cuts_empty = false;   ///< one side holds (almost) no reference: see kNearlyEmpty
    double cost = INFINITY;
};

/// Per-axis bins of a range of references: how many start / end in each bin, and the lowest
/// start / highest end in it (the tight planes next to each boundary). Only the first `count`
/// bins of each axis are used (and cleared by reset): small nodes do not pay for kMaxBins.
struct Bins {
    std::array<std::array<uint32_t, kMaxBins>, 3> starts;
    std::array<std::array<uint32_t, kMaxBins>, 3> ends;
    std::array<std::array<float, kMaxBins>, 3> min_start;
    std::array<std::array<float, kMaxBins>, 3> max_end;

    void reset(uint32_t count) noexcept {
        for (int a = 0; a < 3; ++a) {
            std::fill_n(starts[a].begin(), count, 0u);
            std::fill_n(ends[a].begin(), count, 0u);
            std::fill_n(min_start[a].begin(), count, INFINITY);
            std::fill_n(max_end[a].begin(), count, -INFINITY);
        }
    }
    void add(const Bins& other, uint32_t count) noexcept {
        for (int a = 0; a < 3; ++a) {
            for (uint32_t b = 0; b < count; ++b) {
                starts[a][b] += other.starts[a][b];
                ends[a][b] += other.ends[a][b];
                min_start[a][b] = std::min(min_start[a][b], other.min_start[a][b]);
                max_end[a][b] = std::max(max_end[a][b], other.max_end[a][b]);
            }
        }
    }
};

/// Calls body(begin, end) for the chunks of [0, n), in parallel when n is big.
template <typename Body>
void for_chunks(size_t n, const Body& body) {
    const size_t chunks = (n + kChunkRefs - 1) / kChunkRefs;
    if (n < kParallelRefs) {
        for (size_t c = 0; c < chunks; ++c)
            body(c, c * kChunkRefs, std::min(n, (c + 1) * kChunkRefs));
        return;
    }
    tbb::parallel_for(size_t{0}, chunks, [&](size_t c) {
        body(c, c * kChunkRefs, std::min(n, (c + 1) * kChunkRefs));
    });
}

/// Storage kept per thread for reuse (its pages faulted in once, not at every node: on 64
/// bunnies the exact subtrees' triangle lists, now written over their references, and the binned
/// nodes' per-chunk bins were ~60 MB of fresh heap pages). A user takes it whole and gives it back:
/// a task that runs on the same thread meanwhile (at a oneTBB wait point of the user) finds it
/// empty and makes its own.
template <typename T>
class PerThread {
public:
    [[nodiscard]] T take() { return std::move(local_.local()); }
    void give(T&& value) { local_.local() = std::move(value); }

private:
    tbb::enumerable_thread_specific<T> local_;
};

class BinnedBuilder {
public:
    BinnedBuilder(std::span<const TriVerts> tris, const BuildOptions& options,
                  const BinnedParams& params)
        : tris_(tris),
          params_(params),
          cost_(SahCost::from(options)),
          bins_(std::clamp(params.bins, 4u, kMaxBins)),
          max_depth_(static_cast<uint32_t>(std::clamp(options.max_depth, 0, kMaxDepth))),
          exact_(tris, options, params.empty_cuts_in_place, params.prune_sweep) {}

    /// Builds the node of `refs` (tight bounds `geom`) in `cell` into `slot` of `out`.
    void build(SubTree& out, uint32_t slot, const Aabb& cell, Refs&& refs, const Aabb& geom,
               uint32_t depth) {
        if (refs.size() < params_.exact_below || depth >= max_depth_) {
            to_exact(out, slot, cell, std::move(refs), depth);
            return;
        }
        const BinnedSplit split = find_split(cell, refs, geom);
        if (!divides(split, refs.size())) {
            to_exact(out, slot, cell, std::move(refs), depth);
            return;
        }
        divide(out, slot, cell, std::move(refs), split, depth);
    }

    /// Builds the whole tree in `cell` (the root cell) into slot 0 of `out`: the triangles that
    /// `degenerate` does not flag, all in the cell, their vertex bounds `geom` (root_cell).
    void build_root(SubTree& out, const Aabb& cell, const Aabb& geom,
                    const std::vector<uint8_t>& degenerate) {
        // The root's references are the triangles' vertex bounds in the cell, degenerate
        // triangles left out. They are binned straight from the triangles (each chunk of
        // triangles in parallel for big meshes), and written as a list only where a binned split
        // divides the root: where the exact sweep takes the whole mesh (the stadium, a nearly
        // empty cut) the list was 3.6 MB of fresh heap written and read once (~890 page faults a
        // first build, ~10 us each on this project's VM).
        auto root_box = [&](size_t prim, Ref& r) -> const Ref* {
            Aabb box;
            if (degenerate[prim] || !vertex_bounds_in_cell(tris_[prim], cell, box)) return nullptr;
            r = Ref{{box.lo.x, box.lo.y, box.lo.z},
                    {box.hi.x, box.hi.y, box.hi.z},
                    static_cast<uint32_t>(prim)};
            return &r;
        };
        const auto n =
            static_cast<size_t>(std::count(degenerate.begin(), degenerate.end(), uint8_t{0}));
        if (params_.root_from_triangles) {
            // build()'s decision, on the boxes as the list would hold them.
            BinnedSplit split;
            if (n >= params_.exact_below && max_depth_ > 0)
                split = find_split(cell, tris_.size(), n, root_box, geom);
            if (!divides(split, n)) {
                exact_.build_all(out, 0, cell, degenerate, n, 0);
                return;
            }
            divide(out, 0, cell, root_refs(root_box, degenerate, n), split, 0);
        } else {
            build(out, 0, cell, root_refs(root_box, degenerate, n), geom, 0);
        }
    }

private:
    /// The root's list of `n` references, each chunk of triangles writing its own from its first
    /// (the chunks before it hold that many triangles that are not degenerate).
    template <typename RootBox>
    Refs root_refs(const RootBox& root_box, const std::vector<uint8_t>& degenerate, size_t n) {
        const size_t chunks = (tris_.size() + kChunkRefs - 1) / kChunkRefs;
        std::vector<size_t> first(chunks, 0);
        for (size_t c = 1; c < chunks; ++c)
            first[c] = first[c - 1] +
                       static_cast<size_t>(std::count(degenerate.begin() + (c - 1) * kChunkRefs,
                                                      degenerate.begin() + c * kChunkRefs, 0));
        Refs refs = arena_.take(n);
        for_chunks(tris_.size(), [&](size_t c, size_t begin, size_t end) {
            Ref* dst = refs.data() + first[c];
            for (size_t prim = begin; prim < end; ++prim)
                if (root_box(prim, *dst)) ++dst;
        });
        return refs;
    }

    /// Whether a node of `n` references is divided at its best binned split (else the exact
    /// sweep builds it). A node whose best binned split cuts off (nearly) empty space goes to the
    /// exact sweep too: its geometry is concentrated in a few bins, and their coarse boundaries
    /// miss the split through it that the exact sweep finds (the stadium: see kNearlyEmpty).
    [[nodiscard]] bool divides(const BinnedSplit& split, size_t n) const noexcept {
        return split.valid && split.cost < cost_.leaf(static_cast<uint32_t>(n)) &&
               !split.cuts_empty;
    }

    /// Divides the node of `refs` in `cell` at `split` and builds its children.
    void divide(SubTree& out, uint32_t slot, const Aabb& cell, Refs&& refs,
                const BinnedSplit& split, uint32_t depth) {
        Aabb left_cell = cell, right_cell = cell;
        left_cell.hi[split.axis] = split.pos;
        right_cell.lo[split.axis] = split.pos;
        Refs left, right;
        Aabb left_geom, right_geom;
        partition(refs, split, left, right, left_geom, right_geom);
        arena_.give(std::move(refs));  // the parent's references, for the children's children
        if (left.size() + right.size() >= kParallelSubtrees) {
            // The left child straight into `out`, the right one apart and spliced in after it
            // (deferred: copied once, when the whole tree is done): the same layout as building
            // both apart.
            const uint32_t first = add_child_pair(out, slot, split.axis, split.pos);
            SubTree right_tree;
            tbb::parallel_invoke(
                [&] { build(out, first, left_cell, std::move(left), left_geom, depth + 1); },
                [&] { build(right_tree, 0, right_cell, std::move(right), right_geom, depth + 1); });
            defer_splice(out, first + 1, std::move(right_tree));
        } else {
            const uint32_t first = add_child_pair(out, slot, split.axis, split.pos);
            build(out, first, left_cell, std::move(left), left_geom, depth + 1);
            build(out, first + 1, right_cell, std::move(right), right_geom, depth + 1);
        }
    }

    /// Clips the references cut by binned splits to `cell` and builds the node exactly.
    void to_exact(SubTree& out, uint32_t slot, const Aabb& cell, Refs&& refs, uint32_t depth) {
        // The exact builder's boxes are written over the references, each after its reference
        // is read (a PrimBox takes a Ref's place, and the m-th box is written after the i-th
        // reference is read, m <= i): a list of its own was fresh memory for every thread's
        // biggest subtree (the stadium hands its whole root over: 3.6 MB, ~900 page faults on
        // one thread per build).
        static_assert(sizeof(PrimBox) == sizeof(Ref) && alignof(PrimBox) <= alignof(Ref));
        static_assert(std::is_trivially_copyable_v<PrimBox> &&
                      std::is_trivially_destructible_v<Ref>);
        auto* const slots = static_cast<void*>(refs.data());
        size_t m = 0;
        for (size_t i = 0; i < refs.size(); ++i) {
            const Ref r = refs.data()[i];
            PrimBox p{r.box(), r.prim_and_flag & ~kCut};
            // An uncut reference's bounds are its vertex bounds, which the clipped bounds equal
            // for a triangle inside the cell. A cut one was sent to both sides by its bounds
            // alone: the triangle itself may miss this cell, and is then dropped here.
            if (r.prim_and_flag & kCut) {
                const TriVerts& tri = tris_[p.prim];
                if (!clip_unless_missing(tri, cell, p.box)) continue;
            }
            ::new (static_cast<unsigned char*>(slots) + m * sizeof(PrimBox)) PrimBox(p);
            ++m;
        }
        const std::span<const PrimBox> prims(std::launder(reinterpret_cast<const PrimBox*>(slots)),
                                             m);
        exact_.build(out, slot, cell, prims, depth);
        arena_.give(std::move(refs));
    }

    /// The number of bins per axis for a node of `n` references: BinnedParams::bins, fewer for
    /// small nodes (evaluating the candidates costs O(bins), binning O(n)).
    [[nodiscard]] uint32_t bin_count(size_t n) const noexcept {
        const auto wanted = static_cast<uint32_t>(std::min<size_t>(n / kRefsPerBin, kMaxBins));
        return std::clamp(wanted, std::min(kMinBins, bins_), bins_);
    }

    BinnedSplit find_split(const Aabb& cell, const Refs& refs, const Aabb& geom) {
        return find_split(
            cell, refs.size(), refs.size(), [&](size_t i, Ref&) { return &refs[i]; }, geom);
    }

    /// The best binned split of the node of the references boxes(i, scratch) gives for i in
    /// [0, items) (null: none at i; `n` in all), in `cell`, with tight bounds `geom`.
    template <typename Boxes>
    BinnedSplit find_split(const Aabb& cell, size_t items, size_t n, const Boxes& boxes,
                           const Aabb& geom) {
        const double area = half_area(cell);
        if (!(area > 0)) return {};
        const double inv_area = 1.0 / area;
        const uint32_t bins = bin_count(n);
        Bins total;
        return best_binned_split(cell, inv_area, items, n, boxes, geom, bins, total);
    }

    /// Bins the references (as find_split gives them), each axis over [range.lo, range.hi] of
    /// that axis (references outside fall into the end bins), and returns the best candidate
    /// plane. `total` is scratch space.
    template <typename Boxes>
    BinnedSplit best_binned_split(const Aabb& cell, double inv_area, size_t items, size_t n_refs,
                                  const Boxes& boxes, const Aabb& range, uint32_t bins,
                                  Bins& total) {
        std::array<BinMap, 3> maps;
        for (int a = 0; a < 3; ++a) {
            const double extent = double{range.hi[a]} - range.lo[a];
            maps[a] = extent > 0 ? BinMap{range.lo[a], bins / extent, bins} : BinMap{};
        }

        // One pass over the references bins all three axes.
        const BoundsBinMap map6(maps);
        auto bin_range = [&](Bins& into, size_t begin, size_t end) {
            into.reset(bins);
            std::array<uint32_t, 6> b{};
            for (size_t i = begin; i < end; ++i) {
                Ref scratch;
                const Ref* const r = boxes(i, scratch);
                if (r == nullptr) continue;
                map6(r->lo, r->hi, b);
                for (int a = 0; a < 3; ++a) {
                    const float lo = r->lo[a], hi = r->hi[a];
                    const uint32_t bl = b[BoundsBinMap::kLo[a]], bh = b[BoundsBinMap::kHi[a]];
                    ++into.starts[a][bl];
                    ++into.ends[a][bh];
                    into.min_start[a][bl] = std::min(into.min_start[a][bl], lo);
                    into.max_end[a][bh] = std::max(into.max_end[a][bh], hi);
                }
            }
        };
        if (items <= kChunkRefs) {
            bin_range(total, 0, items);
        } else {
            const size_t chunks = (items + kChunkRefs - 1) / kChunkRefs;
            // Kept per thread (12 KiB a chunk, up to ~600 chunks on 64 bunnies' root); not
            // cleared here: bin_range resets the `bins` bins it uses.
            std::vector<Bins> partial = chunk_bins_.take();
            if (partial.size() < chunks) partial.resize(chunks);
            for_chunks(items, [&](size_t c, size_t begin, size_t end) {
                bin_range(partial[c], begin, end);
            });
            total.reset(bins);
            for (size_t c = 0; c < chunks; ++c) total.add(partial[c], bins);
            chunk_bins_.give(std::move(partial));
        }

        const auto n = static_cast<uint32_t>(n_refs);
        BinnedSplit best;
        for (int a = 0; a < 3; ++a) {
            const float lo = cell.lo[a], hi = cell.hi[a];
            if (!(lo < hi)) continue;  // flat along this axis: nothing to split
            const int a1 = (a + 1) % 3, a2 = (a + 2) % 3;
            const double e1 = double{cell.hi[a1]} - cell.lo[a1];
            const double e2 = double{cell.hi[a2]} - cell.lo[a2];
            const double cap = e1 * e2, ring = e1 + e2;
            // Candidates strictly inside the cell; ties keep the earlier (lower axis, lower pos).
            auto consider = [&](float pos, uint32_t nl, uint32_t nr, bool planar_left) {
                if (!(pos > lo && pos < hi)) return;
                const double pl = (cap + ring * (double{pos} - lo)) * inv_area;
                const double pr = (cap + ring * (double{hi} - pos)) * inv_area;
                const double cost = cost_.split(pl, pr, nl, nr);
                if (cost < best.cost)
                    best = {true, a, pos, planar_left, std::min(nl, nr) <= n / kNearlyEmpty, cost};
            };
            // At each bin boundary b (b = 0 and b = bins: the ends of the range), three planes
            // share the same estimated counts: the boundary itself, the highest end of the
            // references ending below it (references in that plane go left) and the lowest start
            // of those starting above it (they go right). The two tight planes are where the
            // empty space between neighbouring geometry is cut off, as the exact sweep would.
            std::array<float, kMaxBins + 1> lowest_start_above;
            lowest_start_above[bins] = INFINITY;
            for (uint32_t b = bins; b-- > 0;)
                lowest_start_above[b] = std::min(lowest_start_above[b + 1], total.min_start[a][b]);
            const double extent = double{range.hi[a]} - range.lo[a];
            uint32_t nl = 0, nr = n;
            float highest_end_below = -INFINITY;
            for (uint32_t b = 0; b <= bins; ++b) {
                if (b > 0) {
                    nl += total.starts[a][b - 1];
                    nr -= total.ends[a][b - 1];
                    highest_end_below = std::max(highest_end_below, total.max_end[a][b - 1]);
                }
                consider(highest_end_below, nl, nr, true);
                if (b > 0 && b < bins && extent > 0) {
                    const auto pos = static_cast<float>(range.lo[a] + extent * b / bins);
                    if (pos > highest_end_below && pos < lowest_start_above[b])
                        consider(pos, nl, nr, false);
                }
                consider(lowest_start_above[b], nl, nr, false);
            }
        }
        return best;
    }

    /// Splits the references at the plane, keeping their order on each side. A reference that
    /// crosses the plane goes to both sides, its bounds cut at the plane and marked for clipping.
    /// `left_geom` / `right_geom`: the tight bounds of each side's references (their
    /// lowest lower and highest upper bounds), gathered while they are written.
    void partition(const Refs& refs, const BinnedSplit& split, Refs& left, Refs& right,
                   Aabb& left_geom, Aabb& right_geom) {
        const int k = split.axis;
        const float p = split.pos;
        const bool planar_left = split.planar_left;
        // 1: left only, 2: right only, 3: both.
        auto side = [&](const Ref& r) -> uint32_t {
            const float lo = r.lo[k], hi = r.hi[k];
            if (hi < p || (hi == p && (lo < p || planar_left))) return 1;
            if (lo >= p) return 2;
            return 3;
        };
        auto place = [&](const Ref& r, uint32_t s, Ref*& l, Ref*& rr, Aabb& lb, Aabb& rb) {
            if (s == 3) {
                Ref cut = r;
                cut.prim_and_flag |= kCut;
                cut.hi[k] = p;
                *l++ = cut;
                extend(lb, cut);
                cut.hi[k] = r.hi[k];
                cut.lo[k] = p;
                *rr++ = cut;
                extend(rb, cut);
            } else if (s == 1) {
                *l++ = r;
                extend(lb, r);
            } else {
                *rr++ = r;
                extend(rb, r);
            }
        };
        const size_t chunks = (refs.size() + kChunkRefs - 1) / kChunkRefs;
        std::vector<std::array<size_t, 2>> counts(chunks + 1);
        for_chunks(refs.size(), [&](size_t c, size_t begin, size_t end) {
            size_t nl = 0, nr = 0;
            for (size_t i = begin; i < end; ++i) {
                const uint32_t s = side(refs[i]);
                nl += s & 1u;
                nr += s >> 1;
            }
            counts[c + 1] = {nl, nr};
        });
        for (size_t c = 1; c <= chunks; ++c) {
            counts[c][0] += counts[c - 1][0];
            counts[c][1] += counts[c - 1][1];
        }
        left = arena_.take(counts[chunks][0]);
        right = arena_.take(counts[chunks][1]);
        // Bounds per chunk, combined in chunk order (min and max: the same at any thread count).
        std::vector<std::array<Aabb, 2>> bounds(chunks);
        for_chunks(refs.size(), [&](size_t c, size_t begin, size_t end) {
            Ref* l = left.data() + counts[c][0];
            Ref* r = right.data() + counts[c][1];
            Aabb lb, rb;
            for (size_t i = begin; i < end; ++i) place(refs[i], side(refs[i]), l, r, lb, rb);
            bounds[c] = {lb, rb};
        });
        left_geom = right_geom = Aabb{};
        for (const auto& b : bounds) {
            extend(left_geom, b[0]);
            extend(right_geom, b[1]);
        }
    }

    std::span<const TriVerts> tris_;
    BinnedParams params_;
    SahCost cost_;
    uint32_t bins_;
    uint32_t max_depth_;
    ExactSahBuilder exact_;
    RefArena arena_;
    PerThread<std::vector<Bins>> chunk_bins_;  ///< best_binned_split's, one per chunk
};

}  // namespace

void build_binned(std::span<const TriVerts> tris, const std::vector<uint8_t>& degenerate,
                  const Aabb& root, const Aabb& tight, const BuildOptions& options,
                  const BinnedParams& params, SubTree& out) {
    BinnedBuilder(tris, options, params).build_root(out, root, tight, degenerate);
}

}  // namespace kdrt::detail
