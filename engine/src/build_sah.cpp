// The cost-optimised kD-tree builder: Wald & Havran 2006, "On building fast kd-trees for ray
// tracing, and on doing that in O(N log N)".
//
// Every node keeps, per axis, a list of events sorted by (position, type, triangle). An event is
// a triangle's clipped extent starting or ending at a position, or the triangle lying in a plane
// there (planar). One O(n) sweep per axis evaluates the surface area heuristic at every distinct
// event position ("perfect splits": the candidates come from the triangles clipped to the cell).
// Splitting a node partitions the sorted lists without re-sorting; only the triangles that straddle
// the plane are clipped to each child and their (few) new events sorted and merged in.

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <vector>

#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_invoke.h>
#include <tbb/parallel_sort.h>
#include <tbb/task_arena.h>

#include "build_common.h"
#include "build_internal.h"

namespace kdrt::detail {
namespace {

// An event packed into 64 bits so that sorting the integers sorts by (position, type, prim):
// bits 32..63 the position as an order-preserving integer, bits 30..31 the type, bits 0..29 the
// triangle. End < Planar < Start at equal positions, the order the sweep needs.
using Event = uint64_t;
static_assert(sizeof(Event) == 8);

enum EventType : uint32_t { kEnd = 0, kPlanar = 1, kStart = 2 };

constexpr uint32_t ordered_bits(float f) noexcept {
    const uint32_t b = std::bit_cast<uint32_t>(f + 0.0f);  // -0 -> +0: one key per plane
    return (b & 0x80000000u) ? ~b : (b | 0x80000000u);
}
constexpr float from_ordered_bits(uint32_t o) noexcept {
    return std::bit_cast<float>((o & 0x80000000u) ? (o & 0x7FFFFFFFu) : ~o);
}
constexpr Event make_event(float pos, EventType type, uint32_t prim) noexcept {
    return (uint64_t{ordered_bits(pos)} << 32) | (uint64_t{type} << 30) | prim;
}
constexpr uint32_t event_key(Event e) noexcept { return static_cast<uint32_t>(e >> 32); }
constexpr float event_pos(Event e) noexcept { return from_ordered_bits(event_key(e)); }
constexpr uint32_t event_type(Event e) noexcept { return static_cast<uint32_t>(e >> 30) & 3u; }
constexpr uint32_t event_prim(Event e) noexcept { return static_cast<uint32_t>(e) & 0x3FFFFFFFu; }

using EventLists = std::array<std::vector<Event>, 3>;

/// Appends the events of a triangle whose clipped bounds in the cell are `box`.
void add_events(EventLists& lists, const Aabb& box, uint32_t prim) {
    for (int a = 0; a < 3; ++a) {
        if (box.lo[a] == box.hi[a]) {
            lists[a].push_back(make_event(box.lo[a], kPlanar, prim));
        } else {
            lists[a].push_back(make_event(box.lo[a], kStart, prim));
            lists[a].push_back(make_event(box.hi[a], kEnd, prim));
        }
    }
}

/// Bounds of triangle `tri` clipped to the closed box `cell` (Sutherland-Hodgman in double),
/// rounded outwards to float and clamped to the cell. Returns false if nothing remains.
bool clipped_bounds(const TriVerts& tri, const Aabb& cell, Aabb& out) {
    using P = std::array<double, 3>;
    std::array<P, 16> poly_a, poly_b;
    int n = 3;
    for (int a = 0; a < 3; ++a) {
        poly_a[0][a] = tri.v0[a];
        poly_a[1][a] = tri.v1[a];
        poly_a[2][a] = tri.v2[a];
    }
    P* src = poly_a.data();
    P* dst = poly_b.data();
    for (int a = 0; a < 3 && n > 0; ++a) {
        for (int side = 0; side < 2 && n > 0; ++side) {
            const double bound = side == 0 ? cell.lo[a] : cell.hi[a];
            auto inside = [&](const P& p) { return side == 0 ? p[a] >= bound : p[a] <= bound; };
            bool all_inside = true;
            for (int i = 0; i < n && all_inside; ++i) all_inside = inside(src[i]);
            if (all_inside) continue;  // this plane cuts nothing off (the common case)
            int m = 0;
            for (int i = 0; i < n; ++i) {
                const P& cur = src[i];
                const P& next = src[(i + 1) % n];
                const bool in_cur = inside(cur), in_next = inside(next);
                if (in_cur) dst[m++] = cur;
                if (in_cur != in_next) {
                    const double s = (bound - cur[a]) / (next[a] - cur[a]);
                    P q;
                    for (int b = 0; b < 3; ++b) q[b] = cur[b] + s * (next[b] - cur[b]);
                    q[a] = bound;
                    dst[m++] = q;
                }
            }
            n = m;
            std::swap(src, dst);
        }
    }
    if (n == 0) return false;
    for (int a = 0; a < 3; ++a) {
        double lo = src[0][a], hi = src[0][a];
        for (int i = 1; i < n; ++i) {
            lo = std::min(lo, src[i][a]);
            hi = std::max(hi, src[i][a]);
        }
        float flo = static_cast<float>(lo), fhi = static_cast<float>(hi);
        if (static_cast<double>(flo) > lo) flo = std::nextafter(flo, -INFINITY);
        if (static_cast<double>(fhi) < hi) fhi = std::nextafter(fhi, INFINITY);
        out.lo[a] = std::max(flo, cell.lo[a]);
        out.hi[a] = std::min(fhi, cell.hi[a]);
        if (out.lo[a] > out.hi[a]) return false;
    }
    return true;
}

/// Bounds of a triangle's vertices intersected with `cell`; false if they do not overlap.
bool vertex_bounds_in(const TriVerts& tri, const Aabb& cell, Aabb& out) {
    for (int a = 0; a < 3; ++a) {
        const float lo = std::min({tri.v0[a], tri.v1[a], tri.v2[a]});
        const float hi = std::max({tri.v0[a], tri.v1[a], tri.v2[a]});
        out.lo[a] = std::max(lo, cell.lo[a]);
        out.hi[a] = std::min(hi, cell.hi[a]);
        if (out.lo[a] > out.hi[a]) return false;
    }
    return true;
}

/// Merges the sorted `extra` into the sorted `dst` in place, from the back (no temporary).
void merge_into(std::vector<Event>& dst, const std::vector<Event>& extra) {
    if (extra.empty()) return;
    size_t i = dst.size(), j = extra.size();
    dst.resize(i + j);
    size_t k = dst.size();
    while (j > 0) {
        if (i > 0 && dst[i - 1] > extra[j - 1]) {
            dst[--k] = dst[--i];
        } else {
            dst[--k] = extra[--j];
        }
    }
}

double half_area(const Aabb& b) noexcept {
    const double x = double{b.hi.x} - b.lo.x, y = double{b.hi.y} - b.lo.y, z = double{b.hi.z} - b.lo.z;
    return x * y + y * z + z * x;
}

struct Split {
    bool valid = false;
    int axis = 0;
    float pos = 0;
    bool planar_left = true;
    double cost = INFINITY;
};

struct NodeInput {
    Aabb cell;
    EventLists events;
    uint32_t prim_count = 0;
    uint32_t depth = 0;
};

enum Side : uint8_t { kBoth = 0, kLeftOnly = 1, kRightOnly = 2 };

constexpr uint32_t kParallelSubtrees = 4096;  // nodes at least this big build children concurrently
constexpr size_t kParallelAxes = 1u << 15;    // events per axis above which the axes run concurrently

class SahBuilder {
public:
    SahBuilder(const std::vector<TriVerts>& tris, const BuildOptions& options)
        : tris_(tris), options_(options),
          max_depth_(static_cast<uint32_t>(std::clamp(options.max_depth, 0, kMaxDepth))),
          sides_([n = tris.size()] { return std::vector<uint8_t>(n); }) {}

    void build(SubTree& out, uint32_t slot, NodeInput&& in) {
        const Split split = in.depth < max_depth_ && in.prim_count > 0 ? find_split(in) : Split{};
        const double leaf_cost = double{options_.intersection_cost} * in.prim_count;
        if (!split.valid || !(split.cost < leaf_cost)) {
            make_leaf(out, slot, leaf_prims(in));
            out.max_depth = std::max(out.max_depth, in.depth);
            return;
        }
        NodeInput left, right;
        partition(in, split, left, right);
        in = NodeInput{};  // free the parent's events before descending
        if (left.prim_count + right.prim_count >= kParallelSubtrees) {
            SubTree left_tree, right_tree;
            tbb::parallel_invoke([&] { build(left_tree, 0, std::move(left)); },
                                 [&] { build(right_tree, 0, std::move(right)); });
            const uint32_t first = add_child_pair(out, slot, split.axis, split.pos);
            splice(out, first, left_tree);
            splice(out, first + 1, right_tree);
        } else {
            const uint32_t first = add_child_pair(out, slot, split.axis, split.pos);
            build(out, first, std::move(left));
            build(out, first + 1, std::move(right));
        }
    }

private:
    /// The SAH of every candidate plane on one axis, swept in one pass over its sorted events.
    Split sweep_axis(const NodeInput& in, int axis) const {
        Split best;
        const Aabb& cell = in.cell;
        if (!(cell.lo[axis] < cell.hi[axis])) return best;  // flat along this axis: nothing to split
        const double area = half_area(cell);
        if (!(area > 0)) return best;
        const double inv_area = 1.0 / area;
        const int a1 = (axis + 1) % 3, a2 = (axis + 2) % 3;
        const double e1 = double{cell.hi[a1]} - cell.lo[a1], e2 = double{cell.hi[a2]} - cell.lo[a2];
        const double cap = e1 * e2, ring = e1 + e2;
        const double c_trav = options_.traversal_cost, c_isect = options_.intersection_cost;
        const double empty_scale = 1.0 - double{options_.empty_bonus};
        const uint32_t n_total = in.prim_count;

        const std::vector<Event>& ev = in.events[axis];
        uint32_t n_left = 0, n_right = n_total;
        size_t i = 0;
        while (i < ev.size()) {
            const uint32_t key = event_key(ev[i]);
            uint32_t ending = 0, planar = 0, starting = 0;
            while (i < ev.size() && event_key(ev[i]) == key && event_type(ev[i]) == kEnd) ++ending, ++i;
            while (i < ev.size() && event_key(ev[i]) == key && event_type(ev[i]) == kPlanar) ++planar, ++i;
            while (i < ev.size() && event_key(ev[i]) == key && event_type(ev[i]) == kStart) ++starting, ++i;
            n_right -= planar + ending;
            const float pos = from_ordered_bits(key);
            if (pos >= cell.lo[axis] && pos <= cell.hi[axis]) {
                const double pl = (cap + ring * (double{pos} - cell.lo[axis])) * inv_area;
                const double pr = (cap + ring * (double{cell.hi[axis]} - pos)) * inv_area;
                // Planar triangles go left or right, whichever is cheaper (Wald & Havran 2006);
                // without any, both placements are the same split.
                for (int planar_left = 1; planar_left >= (planar ? 0 : 1); --planar_left) {
                    const uint32_t nl = n_left + (planar_left ? planar : 0);
                    const uint32_t nr = n_right + (planar_left ? 0 : planar);
                    // A plane on the cell boundary leaves one child the whole cell: it must then
                    // hold fewer triangles, or the split makes no progress.
                    if (pos == cell.lo[axis] && nr >= n_total) continue;
                    if (pos == cell.hi[axis] && nl >= n_total) continue;
                    double cost = c_isect * (pl * nl + pr * nr);
                    if (nl == 0 || nr == 0) cost *= empty_scale;
                    cost += c_trav;
                    if (cost < best.cost) best = {true, axis, pos, planar_left == 1, cost};
                }
            }
            n_left += starting + planar;
        }
        return best;
    }

    Split find_split(const NodeInput& in) const {
        std::array<Split, 3> per_axis;
        if (in.events[0].size() >= kParallelAxes) {
            tbb::this_task_arena::isolate([&] {
                tbb::parallel_invoke([&] { per_axis[0] = sweep_axis(in, 0); },
                                     [&] { per_axis[1] = sweep_axis(in, 1); },
                                     [&] { per_axis[2] = sweep_axis(in, 2); });
            });
        } else {
            for (int a = 0; a < 3; ++a) per_axis[a] = sweep_axis(in, a);
        }
        Split best = per_axis[0];
        for (int a = 1; a < 3; ++a)
            if (per_axis[a].cost < best.cost) best = per_axis[a];  // ties keep the lower axis
        return best;
    }

    std::vector<uint32_t> leaf_prims(const NodeInput& in) const {
        std::vector<uint32_t> prims;
        prims.reserve(in.prim_count);
        for (Event e : in.events[0])
            if (event_type(e) != kEnd) prims.push_back(event_prim(e));
        std::sort(prims.begin(), prims.end());
        return prims;
    }

    /// Classifies the triangles against the split and builds the children's sorted event lists.
    void partition(const NodeInput& in, const Split& split, NodeInput& left, NodeInput& right) {
        const int k = split.axis;
        const float p = split.pos;
        left.cell = in.cell;
        right.cell = in.cell;
        left.cell.hi[k] = p;
        right.cell.lo[k] = p;
        left.depth = right.depth = in.depth + 1;

        // The side array is per thread and sized for all triangles; it is written and read only
        // inside this call, whose parallel part is isolated so no other node's work can run on
        // this thread in between.
        std::vector<uint8_t>& side = sides_.local();
        std::vector<uint32_t> straddling;
        uint32_t left_only = 0, right_only = 0;
        for (Event e : in.events[k])
            if (event_type(e) != kEnd) side[event_prim(e)] = kBoth;
        for (Event e : in.events[k]) {
            const uint32_t type = event_type(e);
            const float pos = event_pos(e);
            const uint32_t prim = event_prim(e);
            if (type == kEnd && pos <= p) {
                side[prim] = kLeftOnly;
            } else if (type == kStart && pos >= p) {
                side[prim] = kRightOnly;
            } else if (type == kPlanar) {
                const bool to_left = pos < p || (pos == p && split.planar_left);
                side[prim] = to_left ? kLeftOnly : kRightOnly;
            }
        }
        for (Event e : in.events[k]) {
            if (event_type(e) == kEnd) continue;
            const uint8_t s = side[event_prim(e)];
            if (s == kLeftOnly) ++left_only;
            else if (s == kRightOnly) ++right_only;
            else straddling.push_back(event_prim(e));
        }
        std::sort(straddling.begin(), straddling.end());

        // Straddling triangles are clipped to each child ("perfect splits"); their new events are
        // few (O(sqrt N) on typical meshes), sorted here and merged into the filtered lists.
        EventLists new_left, new_right;
        for (uint32_t prim : straddling) {
            Aabb box;
            if (clipped_bounds(tris_[prim], left.cell, box) || vertex_bounds_in(tris_[prim], left.cell, box)) {
                add_events(new_left, box, prim);
                ++left_only;
            }
            if (clipped_bounds(tris_[prim], right.cell, box) || vertex_bounds_in(tris_[prim], right.cell, box)) {
                add_events(new_right, box, prim);
                ++right_only;
            }
        }
        left.prim_count = left_only;
        right.prim_count = right_only;

        auto split_axis = [&](int a) {
            std::sort(new_left[a].begin(), new_left[a].end());
            std::sort(new_right[a].begin(), new_right[a].end());
            // At most two events per triangle on each side (prim_count includes the straddlers).
            std::vector<Event>& l = left.events[a];
            std::vector<Event>& r = right.events[a];
            l.reserve(2 * size_t{left.prim_count});
            r.reserve(2 * size_t{right.prim_count});
            for (Event e : in.events[a]) {
                const uint8_t s = side[event_prim(e)];
                if (s == kLeftOnly) l.push_back(e);
                else if (s == kRightOnly) r.push_back(e);
            }
            merge_into(l, new_left[a]);
            merge_into(r, new_right[a]);
        };
        if (in.events[k].size() >= kParallelAxes) {
            tbb::this_task_arena::isolate([&] {
                tbb::parallel_invoke([&] { split_axis(0); }, [&] { split_axis(1); }, [&] { split_axis(2); });
            });
        } else {
            for (int a = 0; a < 3; ++a) split_axis(a);
        }
    }

    const std::vector<TriVerts>& tris_;
    BuildOptions options_;
    uint32_t max_depth_;
    tbb::enumerable_thread_specific<std::vector<uint8_t>> sides_;
};

}  // namespace

void build_sah(const std::vector<TriVerts>& tris, const std::vector<uint8_t>& degenerate, const Aabb& root,
               const BuildOptions& options, SubTree& out) {
    NodeInput in;
    in.cell = root;
    for (uint32_t prim = 0; prim < tris.size(); ++prim) {
        if (degenerate[prim]) continue;
        Aabb box;
        if (!vertex_bounds_in(tris[prim], root, box)) continue;
        add_events(in.events, box, prim);
        ++in.prim_count;
    }
    tbb::parallel_invoke([&] { tbb::parallel_sort(in.events[0].begin(), in.events[0].end()); },
                         [&] { tbb::parallel_sort(in.events[1].begin(), in.events[1].end()); },
                         [&] { tbb::parallel_sort(in.events[2].begin(), in.events[2].end()); });
    SahBuilder builder(tris, options);
    builder.build(out, 0, std::move(in));
}

}  // namespace kdrt::detail
