// The cost-optimised kD-tree builder: Wald & Havran 2006, "On building fast kd-trees for ray
// tracing, and on doing that in O(N log N)".
//
// Every node keeps, per axis, a list of events sorted by (position, type, triangle). An event is
// a triangle's clipped extent starting or ending at a position, or the triangle lying in a plane
// there (planar). One O(n) sweep per axis evaluates the surface area heuristic at every distinct
// event position ("perfect splits": the candidates come from the triangles clipped to the cell).
// Splitting a node partitions the sorted lists without re-sorting; only the triangles that straddle
// the plane are clipped to each child and their (few) new events sorted and merged in.
//
// Performance notes. The output (which events a node holds, which split wins, the leaves) is fully
// determined by the algorithm above and is bit-identical at any thread count; the points below only
// change how fast it is computed. Most of the work is in the many small nodes near the leaves
// (on the bunny, nodes of fewer than 16 triangles see ~40% of all events), so per-node overhead
// matters as much as per-event cost.
//  - A node's three event lists live in one buffer taken from a per-thread pool, so small nodes
//    allocate nothing. Each list is followed by a sentinel, which ends the sweep's inner loop.
//  - The root's events are created in triangle order and radix-sorted (stable) on the position and
//    type bits: the same order as sorting the whole 64-bit events.
//  - The partition classifies all triangles in one pass over the split axis (the list is sorted,
//    so it is three runs: left of, on and right of the plane), then copies each axis into the
//    children in one branch-free pass that also merges in the straddlers' new events.
//  - The sweep counts a position's events in a register (kSweepCounts).
//  - On lists of kPruneFrom events and more, the sweep skips blocks of positions whose lower bound
//    on the SAH shows that no candidate in them can be chosen (sweep_pruned: costing at least
//    the leaf, a lower axis' best, or more than the best found so far). The big nodes' lists
//    too: pruned, the axes one after the other, they cost less than the parallel chunked sweep.
//  - A cut of empty space hands the node's event lists to its non-empty child as they are: that
//    child holds every triangle, none of them cut, so a partition would copy every event
//    unchanged (the stadium: 16% of all events are in such children).
//  - A triangle's side in a partition is one byte per child, the step of that child's output, so
//    the copy of each event adds the two bytes as they are.
//  - Clipping uses the exact double arithmetic of the straightforward version (only the library
//    call of nextafter is replaced by bit arithmetic, checked equal for every finite float).
//  - Without pruning (tests; cost settings the bounds do not hold for), big nodes (the top of
//    the tree, where only one or two nodes exist) sweep their axes in parallel chunks; chunk
//    results are combined in list order, so the chosen split is the one a sequential sweep
//    finds. Subtrees of big nodes are built concurrently, as before.

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <span>
#include <vector>

#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/task_arena.h>

#include "build_common.h"
#include "build_internal.h"
#include "geometry.h"

namespace kdrt::detail {

// The straddlers' new events (NewEvents::finish) are sorted by a quicksort whose partition step
// has no data-dependent branch (Lomuto's scheme with the swap always done and the boundary advanced
// by the compare), so the unpredictable compares of the straddlers' new events cost no mispredicted
// branches; small ranges by insertion, and std::sort past a depth limit (no quadratic case). Events
// are unique (position, type, triangle), so any correct sort gives the same order as std::sort.
void sort_events(uint64_t* first, uint64_t* last) noexcept {
    using Event = uint64_t;
    constexpr ptrdiff_t kInsertion = 24;
    int depth_left = 2 * std::bit_width(static_cast<size_t>(last - first));
    while (last - first > kInsertion) {
        if (depth_left-- == 0) {
            std::sort(first, last);
            return;
        }
        // Median of three as the pivot, moved to the front.
        Event* mid = first + (last - first) / 2;
        if (*mid < *first) std::swap(*mid, *first);
        if (last[-1] < *mid) {
            std::swap(last[-1], *mid);
            if (*mid < *first) std::swap(*mid, *first);
        }
        std::swap(*first, *mid);
        const Event pivot = *first;
        Event* boundary = first + 1;  // [first + 1, boundary) holds the events below the pivot
        for (Event* j = first + 1; j < last; ++j) {
            const Event x = *j;
            *j = *boundary;
            *boundary = x;
            boundary += x < pivot ? 1 : 0;
        }
        std::swap(*first, boundary[-1]);
        // The pivot is at boundary - 1: recurse into the smaller side, loop on the larger.
        if (boundary - 1 - first < last - boundary) {
            sort_events(first, boundary - 1);
            first = boundary;
        } else {
            sort_events(boundary, last);
            last = boundary - 1;
        }
    }
    if (last - first < 2) return;
    for (Event* i = first + 1; i < last; ++i) {
        const Event x = *i;
        Event* j = i;
        for (; j > first && x < j[-1]; --j) *j = j[-1];
        *j = x;
    }
}

namespace {

// An event packed into 64 bits so that sorting the integers sorts by (position, type, prim):
// bits 32..63 the position as an order-preserving integer, bits 30..31 the type, bits 0..29 the
// triangle. End < Planar < Start at equal positions, the order the sweep needs.
using Event = uint64_t;
static_assert(sizeof(Event) == 8);

enum EventType : uint32_t { kEnd = 0, kPlanar = 1, kStart = 2 };

/// Larger than every real event (their type is never 3): ends the merge inputs.
constexpr Event kSentinel = ~Event{0};

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
/// What an event of each type adds to the sweep's per-position counts: ends and planars in the
/// low 32 bits, starts and planars in the high 32 (a position holds under 2^30 events).
constexpr std::array<uint64_t, 4> kSweepCounts = {1, 1 | (uint64_t{1} << 32), uint64_t{1} << 32, 0};
constexpr uint32_t event_key(Event e) noexcept { return static_cast<uint32_t>(e >> 32); }
constexpr uint32_t event_type(Event e) noexcept { return static_cast<uint32_t>(e >> 30) & 3u; }
constexpr uint32_t event_prim(Event e) noexcept { return static_cast<uint32_t>(e) & 0x3FFFFFFFu; }

/// The events of the straddlers clipped into one child, three lists (one per axis) written
/// in place: no capacity check per event. finish() sorts each and closes it with kSentinel.
struct NewEvents {
    std::array<std::vector<Event>, 3> list;
    std::array<size_t, 3> count{};

    /// Room for `prims` triangles' events (at most two per axis) and the sentinel.
    void reset(size_t prims) {
        for (auto& l : list)
            if (l.size() < 2 * prims + 1) l.resize(2 * prims + 1);
        count = {};
    }
    /// Appends the events of a triangle whose clipped bounds in the child are `box`.
    void add(const Aabb& box, uint32_t prim) noexcept {
        for (int a = 0; a < 3; ++a) {
            Event* dst = list[a].data() + count[a];
            if (box.lo[a] == box.hi[a]) {
                dst[0] = make_event(box.lo[a], kPlanar, prim);
                count[a] += 1;
            } else {
                dst[0] = make_event(box.lo[a], kStart, prim);
                dst[1] = make_event(box.hi[a], kEnd, prim);
                count[a] += 2;
            }
        }
    }
    void finish() {
        for (int a = 0; a < 3; ++a) {
            sort_events(list[a].data(), list[a].data() + count[a]);
            list[a][count[a]] = kSentinel;
        }
    }
};

using Point = std::array<double, 3>;

/// std::nextafter(f, -INFINITY) for finite f, without the library call.
inline float next_down(float f) noexcept {
    if (f == 0.0f) return -std::numeric_limits<float>::denorm_min();
    const uint32_t b = std::bit_cast<uint32_t>(f);
    return std::bit_cast<float>(f > 0.0f ? b - 1 : b + 1);
}
/// std::nextafter(f, INFINITY) for finite f.
inline float next_up(float f) noexcept { return -next_down(-f); }

/// One Sutherland-Hodgman step: clips the polygon src[0..n) against the plane p[a] >= bound
/// (kLow) or p[a] <= bound (!kLow) into dst and returns the new vertex count.
template <bool kLow>
int clip_polygon(const Point* src, int n, int a, double bound, Point* dst) {
    int m = 0;
    bool in_cur = kLow ? src[0][a] >= bound : src[0][a] <= bound;
    for (int i = 0; i < n; ++i) {
        const Point& cur = src[i];
        const Point& next = src[i + 1 == n ? 0 : i + 1];
        const bool in_next = kLow ? next[a] >= bound : next[a] <= bound;
        if (in_cur) dst[m++] = cur;
        if (in_cur != in_next) {
            const double s = (bound - cur[a]) / (next[a] - cur[a]);
            Point q;
            for (int b = 0; b < 3; ++b) q[b] = cur[b] + s * (next[b] - cur[b]);
            q[a] = bound;
            dst[m++] = q;
        }
        in_cur = in_next;
    }
    return m;
}

/// A polygon being clipped: up to 16 points (a triangle clipped by 6 planes has at most 9), in
/// one of two buffers, and the bounds of its points, kept as it is clipped: a plane cuts
/// nothing off where the bounds are inside it (the common case, then skipped without a look at
/// the points), and the bounds of what remains need no pass of their own. The bounds are the
/// running std::min / std::max over the points in order, as a pass over them would give (the
/// same value, the sign of a zero included).
struct Polygon {
    std::array<Point, 16> a, b;
    Point* src = a.data();
    Point* dst = b.data();
    int n = 0;
    Point lo, hi;  // bounds of src[0, n)

    explicit Polygon(const TriVerts& tri) noexcept : n(3) {
        for (int k = 0; k < 3; ++k) {
            a[0][k] = tri.v0[k];
            a[1][k] = tri.v1[k];
            a[2][k] = tri.v2[k];
        }
        update_bounds();
    }
    Polygon(const Polygon& other) noexcept : n(other.n), lo(other.lo), hi(other.hi) {
        std::copy(other.src, other.src + other.n, a.data());
    }
    Polygon& operator=(const Polygon&) = delete;

    /// Clips against the planes of `cell` on axes [first_axis, end_axis), low then high plane of
    /// each axis in turn, until nothing remains.
    void clip(const Aabb& cell, int first_axis, int end_axis) noexcept {
        for (int axis = first_axis; axis < end_axis && n > 0; ++axis) {
            // Planes that cut nothing off the current polygon (the common case) are skipped.
            const double cell_lo = cell.lo[axis], cell_hi = cell.hi[axis];
            if (!(lo[axis] >= cell_lo)) {
                n = clip_polygon<true>(src, n, axis, cell_lo, dst);
                std::swap(src, dst);
                if (n == 0) break;
                update_bounds();
            }
            if (!(hi[axis] <= cell_hi)) {
                n = clip_polygon<false>(src, n, axis, cell_hi, dst);
                std::swap(src, dst);
                if (n > 0) update_bounds();
            }
        }
    }

    /// The bounds of what remains, rounded outwards to float and clamped to `cell`; false if
    /// nothing does.
    bool bounds(const Aabb& cell, Aabb& out) const noexcept {
        return n > 0 && rounded_bounds(lo, hi, cell, out);
    }

    /// Points lo / hi (the bounds of a polygon that is not empty) rounded outwards to float and
    /// clamped to `cell`; false if that leaves nothing.
    static bool rounded_bounds(const Point& lo, const Point& hi, const Aabb& cell,
                               Aabb& out) noexcept {
        for (int axis = 0; axis < 3; ++axis) {
            float flo = static_cast<float>(lo[axis]), fhi = static_cast<float>(hi[axis]);
            if (static_cast<double>(flo) > lo[axis]) flo = next_down(flo);
            if (static_cast<double>(fhi) < hi[axis]) fhi = next_up(fhi);
            out.lo[axis] = std::max(flo, cell.lo[axis]);
            out.hi[axis] = std::min(fhi, cell.hi[axis]);
            if (out.lo[axis] > out.hi[axis]) return false;
        }
        return true;
    }

private:
    /// lo / hi of src[0, n), n > 0: x and y two per SSE2 operation (min_pd(x, m) is
    /// x < m ? x : m, std::min(m, x); max_pd(x, m) is x > m ? x : m, std::max(m, x)).
    void update_bounds() noexcept {
        __m128d lo_xy = _mm_loadu_pd(src[0].data()), hi_xy = lo_xy;
        __m128d lo_z = _mm_load_sd(&src[0][2]), hi_z = lo_z;
        for (int i = 1; i < n; ++i) {
            const __m128d xy = _mm_loadu_pd(src[i].data());
            const __m128d z = _mm_load_sd(&src[i][2]);
            lo_xy = _mm_min_pd(xy, lo_xy);
            hi_xy = _mm_max_pd(xy, hi_xy);
            lo_z = _mm_min_sd(z, lo_z);
            hi_z = _mm_max_sd(z, hi_z);
        }
        _mm_storeu_pd(lo.data(), lo_xy);
        _mm_storeu_pd(hi.data(), hi_xy);
        _mm_store_sd(&lo[2], lo_z);
        _mm_store_sd(&hi[2], hi_z);
    }
};

/// Bounds of triangle `tri` clipped to the closed box `cell` (Sutherland-Hodgman in double),
/// rounded outwards to float and clamped to the cell. Returns false if nothing remains.
bool clipped_bounds(const TriVerts& tri, const Aabb& cell, Aabb& out) {
    Polygon poly(tri);
    poly.clip(cell, 0, 3);
    return poly.bounds(cell, out);
}

/// The common case of clipped_bounds_in_children, after the planes of the axes before `axis`:
/// the polygon `poly` reaches past the split plane on both sides and no other plane of either
/// child cuts it. Sutherland-Hodgman at the split plane for both children in one pass over the
/// edges, straight to the two children's bounds (no points written): an edge that crosses the
/// plane for both children (neither end on it) gives both the same point, computed once; one
/// that crosses for one child only (an end on the plane) gives that child the point its own pass
/// would. Each child's bounds are the running min / max over the points its own pass would
/// write, in the same order (from infinities: the first point's min is itself), so the same
/// bounds, a zero's sign included; the later planes are checked on them as Polygon::clip would,
/// and where one would cut, false: the caller clips in full. (bunny: 78% of the straddlers.)
bool split_in_one_pass(const Polygon& poly, const Aabb& left, const Aabb& right, int axis,
                       bool& left_ok, Aabb& left_box, bool& right_ok, Aabb& right_box) noexcept {
    const int n = poly.n;
    const double p = left.hi[axis];
    if (n == 0 || left.hi[axis] != right.lo[axis] || !(poly.lo[axis] >= left.lo[axis]) ||
        !(poly.hi[axis] > p) || !(poly.lo[axis] < p))
        return false;
    const int a = axis;
    const Point* src = poly.src;
    // Bounds kept as update_bounds keeps them: x and y two per SSE2 operation, z apart.
    struct Bounds {
        __m128d lo_xy = _mm_set1_pd(INFINITY), hi_xy = _mm_set1_pd(-INFINITY);
        __m128d lo_z = lo_xy, hi_z = hi_xy;
        int count = 0;
        void add(__m128d xy, __m128d z) noexcept {
            lo_xy = _mm_min_pd(xy, lo_xy), hi_xy = _mm_max_pd(xy, hi_xy);
            lo_z = _mm_min_sd(z, lo_z), hi_z = _mm_max_sd(z, hi_z), ++count;
        }
        void store(Point& lo, Point& hi) const noexcept {
            _mm_storeu_pd(lo.data(), lo_xy), _mm_store_sd(&lo[2], lo_z);
            _mm_storeu_pd(hi.data(), hi_xy), _mm_store_sd(&hi[2], hi_z);
        }
    } l, r;
    bool in_l = src[0][a] <= p, in_r = src[0][a] >= p;
    for (int i = 0; i < n; ++i) {
        const Point& cur = src[i];
        const Point& next = src[i + 1 == n ? 0 : i + 1];
        const bool next_l = next[a] <= p, next_r = next[a] >= p;
        const __m128d xy = _mm_loadu_pd(cur.data()), z = _mm_load_sd(&cur[2]);
        if (in_l) l.add(xy, z);
        if (in_r) r.add(xy, z);
        const bool cross_l = in_l != next_l, cross_r = in_r != next_r;
        if (cross_l || cross_r) {
            const double s = (p - cur[a]) / (next[a] - cur[a]);
            Point q;
            for (int b = 0; b < 3; ++b) q[b] = cur[b] + s * (next[b] - cur[b]);
            q[a] = p;
            const __m128d qxy = _mm_loadu_pd(q.data()), qz = _mm_load_sd(&q[2]);
            if (cross_l) l.add(qxy, qz);
            if (cross_r) r.add(qxy, qz);
        }
        in_l = next_l;
        in_r = next_r;
    }
    const int l_count = l.count, r_count = r.count;
    Point l_lo, l_hi, r_lo, r_hi;
    l.store(l_lo, l_hi);
    r.store(r_lo, r_hi);
    // The planes Polygon::clip would look at next: the right child's high plane on `axis`, then
    // both children's planes on the later axes.
    if (r_count > 0 && !(r_hi[a] <= right.hi[a])) return false;
    for (int b = a + 1; b < 3; ++b) {
        if (l_count > 0 && !(l_lo[b] >= left.lo[b] && l_hi[b] <= left.hi[b])) return false;
        if (r_count > 0 && !(r_lo[b] >= right.lo[b] && r_hi[b] <= right.hi[b])) return false;
    }
    left_ok = l_count > 0 && Polygon::rounded_bounds(l_lo, l_hi, left, left_box);
    right_ok = r_count > 0 && Polygon::rounded_bounds(r_lo, r_hi, right, right_box);
    return true;
}

/// clipped_bounds of `tri` in both children of a split on `axis`, computed together: the
/// children's cells agree on the axes before `axis`, so those planes are clipped once. The same
/// arithmetic in the same order as two clipped_bounds calls, so the same bounds.
void clipped_bounds_in_children(const TriVerts& tri, const Aabb& left, const Aabb& right, int axis,
                                bool& left_ok, Aabb& left_box, bool& right_ok, Aabb& right_box) {
    Polygon poly(tri);
    poly.clip(left, 0, axis);
    if (split_in_one_pass(poly, left, right, axis, left_ok, left_box, right_ok, right_box)) return;
    Polygon right_poly(poly);
    poly.clip(left, axis, 3);
    left_ok = poly.bounds(left, left_box);
    right_poly.clip(right, axis, 3);
    right_ok = right_poly.bounds(right, right_box);
}

struct Split {
    bool valid = false;
    int axis = 0;
    float pos = 0;
    bool planar_left = true;
    double cost = INFINITY;
};

/// Frees an EventBuffer's events: as EventBuffer::make took them, by their capacity.
struct FreeEvents {
    size_t capacity = 0;
    void operator()(Event* p) const noexcept;
};

/// Uninitialised storage for events (no zero-filling of memory that is overwritten anyway).
struct EventBuffer {
    std::unique_ptr<Event[], FreeEvents> data;
    size_t capacity = 0;

    static EventBuffer make(size_t n);
};

/// A node to be built: its cell and its three sorted event lists, axis a at
/// buffer.data[offset[a] .. offset[a] + count[a]), each followed by kSentinel.
struct NodeInput {
    Aabb cell;
    EventBuffer buffer;
    std::array<size_t, 3> offset{};
    std::array<size_t, 3> count{};
    uint32_t prim_count = 0;
    uint32_t depth = 0;

    [[nodiscard]] const Event* events(int a) const noexcept {
        return buffer.data.get() + offset[a];
    }
};

/// Where a triangle's events go in a partition: per child, how far that child's output moves
/// after the event is written there (1: the event is kept, 0: it is overwritten), so that
/// distribute() adds each byte as it is, without decoding a side. A straddler's old events go to
/// neither child (its clipped ones are merged in instead).
struct Side {
    uint8_t left, right;
};
constexpr Side kBoth{0, 0}, kLeftOnly{1, 0}, kRightOnly{0, 1};

constexpr uint32_t kParallelSubtrees = 4096;  // nodes at least this big build children concurrently
constexpr size_t kParallelAxes = 1u
                                 << 15;  // events per axis above which axes/chunks run concurrently
constexpr size_t kChunk = 1u << 14;      // events per chunk of a parallel sweep
constexpr size_t kPooledEvents = 1u << 13;     // buffers up to this size are recycled per thread
constexpr size_t kPoolSlots = 48;              // at most this many free buffers kept per thread
constexpr size_t kBigPooledEvents = 1u << 16;  // ... and bigger ones up to this size
constexpr size_t kBigPoolSlots = 8;            // at most this many of those
constexpr size_t kHugePageEvents = (size_t{2} << 20) / sizeof(Event);  // a 2 MiB page's
constexpr size_t kRadixSortEvents = 1u << 11;  // a node's first sort: radix from this many events
constexpr size_t kMinBlock = 32, kMaxBlock = 64;  // events per block of sweep_pruned
constexpr size_t kPruneFrom = 256;  // events per axis from which the sweep prunes blocks

/// A buffer the per-thread pools do not keep (more than kBigPooledEvents: the nodes of more than
/// ~11k triangles, a subtree root's events, the radix sort's scratch) is tree memory
/// (allocate_tree_memory): from 2 MiB a huge-page mapping of its own, and one freed while the
/// build runs serves its later big buffers and arrays (RecycleTreeMappings). From the heap, a
/// freed big block went back to the kernel, and every big node's children and every sort's
/// scratch were fresh pages to fault in (the stadium: ~3,700 faults a build). Smaller ones, which
/// the pools keep, stay on the heap (its small blocks are reused warm).
///
/// A buffer between the pools' size and a huge page (the children of nodes of ~11k-44k
/// triangles) takes a whole kept huge page where the build has one (a freed bigger buffer's,
/// already touched), else the heap as before: never a fresh mapping, which costs its zeroing
/// where the heap's blocks may be warm from the build before. From the heap they were the
/// stadium's biggest source of fresh pages (`distribute`, ~40% of a first build's faults).
EventBuffer EventBuffer::make(size_t n) {
    if (n > kBigPooledEvents && n < kHugePageEvents) {
        if (void* p = take_kept_tree_memory(kHugePageEvents * sizeof(Event)))
            return {std::unique_ptr<Event[], FreeEvents>(static_cast<Event*>(p),
                                                         FreeEvents{kHugePageEvents}),
                    kHugePageEvents};
    }
    Event* const p = n > kBigPooledEvents
                         ? static_cast<Event*>(allocate_tree_memory(n * sizeof(Event)))
                         : new Event[n];
    return {std::unique_ptr<Event[], FreeEvents>(p, FreeEvents{n}), n};
}

void FreeEvents::operator()(Event* p) const noexcept {
    if (capacity > kBigPooledEvents) {
        free_tree_memory(p, capacity * sizeof(Event));
    } else {
        delete[] p;
    }
}

/// A run of whole positions of one axis' sorted events, ev[begin, end), with the sweep's counts
/// before it and a lower bound on the cost of every candidate in it (sweep_pruned).
struct SweepBlock {
    uint32_t begin, end;
    uint32_t n_left, n_right;
    double bound;
};

/// Per-thread scratch memory. Used only between TBB wait points, or inside isolated parallel
/// regions that touch nothing but the calling node's data, so nested tasks never see it half-used.
struct Scratch {
    /// Per triangle id, written and read within one partition. Not value-initialised: a page of
    /// it is touched first where a partition writes it (a thread that never sees a triangle
    /// never faults in its page; 64 bunnies: 9.7 MB per thread).
    std::unique_ptr<Side[]> side;
    std::vector<EventBuffer> pool;
    std::vector<uint32_t> straddling;
    NewEvents new_left, new_right;
    std::vector<uint32_t> prims;
    std::vector<SweepBlock> blocks;  // find_split's blocks of one axis

    /// Kept buffers of more than kPooledEvents: an exact subtree's root events, a sort's scratch
    /// and the big nodes below the root (64 bunnies' exact subtrees start at up to ~4k
    /// triangles, 25k events). From the heap each time, ~10% of them were fresh pages to fault
    /// in.
    std::vector<EventBuffer> big_pool;

    /// A buffer for at least `n` events, recycled when possible: a small one, the last kept one
    /// that holds them; a big one, the smallest kept one that does. Both are rounded up to a
    /// power of two, so that they fit later nodes too.
    EventBuffer take(size_t n) {
        if (n <= kPooledEvents) {
            for (size_t i = pool.size(); i-- > 0;) {
                if (pool[i].capacity >= n) return take_at(pool, i);
            }
            n = std::max<size_t>(std::bit_ceil(n), 64);
        } else if (n <= kBigPooledEvents) {
            size_t best = big_pool.size();
            for (size_t i = 0; i < big_pool.size(); ++i)
                if (big_pool[i].capacity >= n &&
                    (best == big_pool.size() || big_pool[i].capacity < big_pool[best].capacity))
                    best = i;
            if (best < big_pool.size()) return take_at(big_pool, best);
            n = std::bit_ceil(n);
        }
        return EventBuffer::make(n);
    }
    void give_back(EventBuffer&& b) {
        if (b.capacity != 0 && b.capacity <= kPooledEvents && pool.size() < kPoolSlots) {
            pool.push_back(std::move(b));
        } else if (b.capacity > kPooledEvents && b.capacity <= kBigPooledEvents &&
                   big_pool.size() < kBigPoolSlots) {
            big_pool.push_back(std::move(b));
        }
        b = {};
    }

private:
    static EventBuffer take_at(std::vector<EventBuffer>& from, size_t i) {
        EventBuffer b = std::move(from[i]);
        from[i] = std::move(from.back());
        from.pop_back();
        return b;
    }
};

/// Constants of one axis' SAH evaluation in a node.
struct SweepSetup {
    int axis;
    float lo, hi;
    double cap, ring, inv_area;
    SahCost cost;
    uint32_t n_total;
};

class SahBuilder {
public:
    SahBuilder(std::span<const TriVerts> tris, const BuildOptions& options,
               bool empty_cuts_in_place, bool prune_sweep)
        : tris_(tris),
          cost_(SahCost::from(options)),
          empty_cuts_in_place_(empty_cuts_in_place),
          prune_(prune_sweep),
          max_depth_(static_cast<uint32_t>(std::clamp(options.max_depth, 0, kMaxDepth))),
          scratch_([n = tris.size()] {
              Scratch s;
              s.side = std::make_unique_for_overwrite<Side[]>(n);
              return s;
          }) {}

    /// Builds the subtree of `in` into `slot` of `out`. `scratch` is the calling thread's; a task
    /// that may run on another thread looks up its own.
    void build(SubTree& out, uint32_t slot, NodeInput&& in, Scratch& scratch) {
        const Split split = in.depth < max_depth_ && !cost_.leaf_always_cheaper(in.prim_count)
                                ? find_split(in, scratch)
                                : Split{};
        if (!split.valid || !(split.cost < cost_.leaf(in.prim_count))) {
            make_leaf(out, slot, leaf_prims(in, scratch.prims));
            scratch.give_back(std::move(in.buffer));
            out.max_depth = std::max(out.max_depth, in.depth);
            return;
        }
        if (const int side = empty_cuts_in_place_ ? empty_side(in, split) : -1; side >= 0) {
            // A cut of empty space: the other child holds every triangle, none of them cut, so
            // its event lists are the node's own. They are handed down as they are (no
            // classification, no copy); the empty child is the leaf partition() would give it.
            // The children in partition()'s order (left first), so the leaf takes the same
            // place among the references.
            const uint32_t first = add_child_pair(out, slot, split.axis, split.pos);
            out.max_depth = std::max(out.max_depth, in.depth + 1);
            ++in.depth;
            if (side == 0) {
                make_leaf(out, first, {});
                in.cell.lo[split.axis] = split.pos;
                build(out, first + 1, std::move(in), scratch);
            } else {
                in.cell.hi[split.axis] = split.pos;
                build(out, first, std::move(in), scratch);
                make_leaf(out, first + 1, {});
            }
            return;
        }
        NodeInput left, right;
        partition(in, split, left, right, scratch);
        scratch.give_back(std::move(in.buffer));  // free the parent's events before descending
        if (left.prim_count + right.prim_count >= kParallelSubtrees) {
            // The left child is built straight into `out` (the right task does not touch it),
            // the right one apart and spliced in after it (deferred: copied once, when the
            // whole tree is done): the same layout as building both apart.
            const uint32_t first = add_child_pair(out, slot, split.axis, split.pos);
            SubTree right_tree;
            tbb::parallel_invoke([&] { build(out, first, std::move(left), scratch_.local()); },
                                 [&] { build(right_tree, 0, std::move(right), scratch_.local()); });
            defer_splice(out, first + 1, std::move(right_tree));
        } else {
            const uint32_t first = add_child_pair(out, slot, split.axis, split.pos);
            build(out, first, std::move(left), scratch);
            build(out, first + 1, std::move(right), scratch);
        }
    }

    void build_root(SubTree& out, uint32_t slot, NodeInput&& in) {
        build(out, slot, std::move(in), scratch_.local());
    }

    /// A buffer for `n` events (a subtree root's, a sort's scratch), from the calling thread's
    /// pool, and back to it.
    EventBuffer take_buffer(size_t n) { return scratch_.local().take(n); }
    void give_buffer(EventBuffer&& b) { scratch_.local().give_back(std::move(b)); }

private:
    SweepSetup sweep_setup(const NodeInput& in, int axis, double inv_area) const {
        const Aabb& cell = in.cell;
        const int a1 = (axis + 1) % 3, a2 = (axis + 2) % 3;
        const double e1 = double{cell.hi[a1]} - cell.lo[a1], e2 = double{cell.hi[a2]} - cell.lo[a2];
        return {axis,    cell.lo[axis], cell.hi[axis], e1 * e2,
                e1 + e2, inv_area,      cost_,         in.prim_count};
    }

    /// The SAH of every candidate plane in ev[begin, end) (whole position groups), swept in one
    /// pass; n_left / n_right are the counts before `begin`. Ties keep the earlier candidate.
    /// Positions strictly inside the cell with no planar event (nearly all of them) take one
    /// candidate and no boundary rule; the rest go through the general case. The arithmetic of
    /// each candidate's cost is the same either way, so the same split wins.
    [[gnu::noinline]] static Split sweep(const SweepSetup& s, const Event* ev, size_t begin,
                                         size_t end, uint32_t n_left, uint32_t n_right) {
        // Locals, so that the loop keeps them in registers.
        const double lo = s.lo, hi = s.hi, cap = s.cap, ring = s.ring, inv_area = s.inv_area;
        const SahCost cost = s.cost;
        const uint32_t n_total = s.n_total;
        // pos > lo and pos < hi as integer compares: ordered_bits is monotonic (-0 and +0 share
        // a key, as they compare equal).
        const uint32_t key_lo = ordered_bits(s.lo), key_hi = ordered_bits(s.hi);
        double best_cost = INFINITY;
        uint32_t best_key = 0;
        bool best_planar_left = true;
        size_t i = begin;
        while (i < end) {
            const uint32_t key = event_key(ev[i]);
            // Count the events at this position: ends and planars (low half of `counts`), starts
            // and planars (high half; type 3 never occurs), in a register rather than an array in
            // memory, whose increments of one slot wait for each other. ev[end] is at another
            // position (the next one, or the sentinel after the list). The events below `limit`
            // are at this position (real keys are below ~0u).
            const Event limit = (Event{key} + 1) << 32;
            const size_t first = i;
            uint64_t counts = 0;
            do {
                counts += kSweepCounts[event_type(ev[i])];
                ++i;
            } while (ev[i] < limit);
            const auto leaving = static_cast<uint32_t>(counts);         // ends and planars
            const auto entering = static_cast<uint32_t>(counts >> 32);  // starts and planars
            const uint32_t planar = leaving + entering - static_cast<uint32_t>(i - first);
            n_right -= leaving;
            const double pos = from_ordered_bits(key);
            if (key > key_lo && key < key_hi && planar == 0) {
                const double pl = (cap + ring * (pos - lo)) * inv_area;
                const double pr = (cap + ring * (hi - pos)) * inv_area;
                const double c = cost.split(pl, pr, n_left, n_right);
                // Branch-free update: which candidates win is hard to predict.
                const bool better = c < best_cost;
                best_cost = better ? c : best_cost;
                best_key = better ? key : best_key;
                best_planar_left = better ? true : best_planar_left;
            } else if (key >= key_lo && key <= key_hi) {
                const double pl = (cap + ring * (pos - lo)) * inv_area;
                const double pr = (cap + ring * (hi - pos)) * inv_area;
                // Planar triangles go left or right, whichever is cheaper (Wald & Havran 2006);
                // without any, both placements are the same split.
                for (int planar_left = 1; planar_left >= (planar ? 0 : 1); --planar_left) {
                    const uint32_t nl = n_left + (planar_left ? planar : 0);
                    const uint32_t nr = n_right + (planar_left ? 0 : planar);
                    // A plane on the cell boundary leaves one child the whole cell: it must then
                    // hold fewer triangles, or the split makes no progress.
                    if (key == key_lo && nr >= n_total) continue;
                    if (key == key_hi && nl >= n_total) continue;
                    const double c = cost.split(pl, pr, nl, nr);
                    const bool better = c < best_cost;
                    best_cost = better ? c : best_cost;
                    best_key = better ? key : best_key;
                    best_planar_left = better ? planar_left == 1 : best_planar_left;
                }
            }
            n_left += entering;
        }
        Split best;
        if (best_cost < INFINITY)
            best = {true, s.axis, from_ordered_bits(best_key), best_planar_left, best_cost};
        return best;
    }

    /// Start indices of chunks of about kChunk events of `ev[0, n)`, each at the first event of
    /// a position (so no position is split between chunks), followed by n.
    static std::vector<size_t> chunk_starts(const Event* ev, size_t n) {
        std::vector<size_t> starts{0};
        for (size_t c = kChunk; c < n; c += kChunk) {
            size_t b = std::max(c, starts.back() + 1);
            while (b < n && event_key(ev[b]) == event_key(ev[b - 1])) ++b;
            if (b >= n) break;
            if (b > starts.back()) starts.push_back(b);
        }
        starts.push_back(n);
        return starts;
    }

    /// sweep() over a big list in parallel chunks: one pass counts each chunk's events to get the
    /// counts at its start, a second sweeps the chunks; the first best in list order wins, as in
    /// one sequential sweep.
    static Split sweep_parallel(const SweepSetup& s, const Event* ev, size_t n) {
        const std::vector<size_t> starts = chunk_starts(ev, n);
        const size_t chunks = starts.size() - 1;
        std::vector<std::array<uint32_t, 2>> counts(
            chunks);  // {left += Start + Planar, right -= End + Planar}
        tbb::parallel_for(size_t{0}, chunks, [&](size_t c) {
            uint32_t count[4] = {0, 0, 0, 0};
            for (size_t i = starts[c]; i < starts[c + 1]; ++i) ++count[event_type(ev[i])];
            counts[c] = {count[kStart] + count[kPlanar], count[kEnd] + count[kPlanar]};
        });
        std::vector<Split> best(chunks);
        tbb::parallel_for(size_t{0}, chunks, [&](size_t c) {
            uint32_t n_left = 0, n_right = s.n_total;
            for (size_t d = 0; d < c; ++d) n_left += counts[d][0], n_right -= counts[d][1];
            best[c] = sweep(s, ev, starts[c], starts[c + 1], n_left, n_right);
        });
        Split result;
        for (const Split& b : best)
            if (b.cost < result.cost) result = b;
        return result;
    }

    /// sweep() over ev[0, n) of a node of n_total triangles, with the candidates that cannot be
    /// chosen skipped in blocks. `bound`: only a candidate costing less matters (the node's
    /// leaf cost, or a lower axis' best, which wins ties). The list is cut into blocks of whole
    /// positions; each block gets a lower bound on its candidates' costs, computed with the
    /// sweep's own arithmetic from its smallest left and right probabilities and counts. Every
    /// operation of SahCost::split on non-negative operands is monotone under IEEE rounding (and
    /// -ffp-contract=off keeps each one rounded on its own), so the bound is at most the cost the
    /// sweep computes for any of the block's candidates. The empty bonus (a factor below 1) goes
    /// into a block's bound only where one of its two counts is 0: a candidate's counts are at
    /// least those, so only then may one of its sides be empty (the bonus on every block made
    /// the bounds ~10% loose, and the stadium's big nodes swept nearly all their blocks: sweeping
    /// them pruned instead of in parallel chunks paid only with this). The block of the lowest
    /// bound is swept first; the rest in order, skipped when their bound is at least `bound` or
    /// above the best cost so far (a block whose bound equals it may hold an earlier tie, so it is
    /// swept). The best candidate (lowest cost, earliest on ties) among those costing less than
    /// `bound` is the one sweep() finds; a candidate costing `bound` or more is never chosen by
    /// build().
    static Split sweep_pruned(const SweepSetup& s, const Event* ev, size_t n, double bound,
                              std::vector<SweepBlock>& blocks) {
        const uint32_t key_lo = ordered_bits(s.lo), key_hi = ordered_bits(s.hi);
        const double lo = s.lo, hi = s.hi;
        const double empty_scale = std::min(s.cost.empty_scale, 1.0);
        // Blocks of n / 8 events (kMinBlock to kMaxBlock), extended to the end of their last
        // position.
        const size_t block = std::clamp<size_t>(n / 8, kMinBlock, kMaxBlock);
        blocks.clear();
        uint32_t n_left = 0, n_right = s.n_total;
        size_t best_block = 0;
        double best_bound = INFINITY;
        for (size_t i = 0; i < n;) {
            size_t j = std::min(i + block, n);
            // ev[n] is kSentinel, whose key is no real event's.
            while (event_key(ev[j]) == event_key(ev[j - 1])) ++j;
            // Types are 0 (end), 1 (planar), 2 (start): bit 31 of an event marks a start, bit 30
            // a planar (summed in place, shifted once).
            uint64_t start_bits = 0, planar_bits = 0;
            for (size_t k = i; k < j; ++k) {
                start_bits += ev[k] & (uint64_t{1} << 31);
                planar_bits += ev[k] & (uint64_t{1} << 30);
            }
            const auto starts = static_cast<uint32_t>(start_bits >> 31);
            const auto planars = static_cast<uint32_t>(planar_bits >> 30);
            const uint32_t entering = starts + planars;
            const auto leaving = static_cast<uint32_t>(j - i) - starts;  // ends and planars
            const uint32_t first = std::max(event_key(ev[i]), key_lo);
            const uint32_t last = std::min(event_key(ev[j - 1]), key_hi);
            double lower = INFINITY;  // no candidate in the block
            if (first <= last) {
                // The smallest probabilities: left at the first candidate, right at the last;
                // the smallest counts: left before the block, right after all its events.
                const double pl =
                    (s.cap + s.ring * (double{from_ordered_bits(first)} - lo)) * s.inv_area;
                const double pr =
                    (s.cap + s.ring * (hi - double{from_ordered_bits(last)})) * s.inv_area;
                double c = s.cost.c_isect *
                           (pl * SahCost::tests(n_left) + pr * SahCost::tests(n_right - leaving));
                // The empty bonus only where a candidate of the block may leave a side empty:
                // its counts are at least these, so a side is empty only if its count is 0.
                if (empty_scale < 1.0 && (n_left == 0 || n_right - leaving == 0)) c *= empty_scale;
                lower = c + s.cost.c_trav;
                if (!(lower == lower)) lower = -INFINITY;  // NaN: sweep it
            }
            blocks.push_back(
                {static_cast<uint32_t>(i), static_cast<uint32_t>(j), n_left, n_right, lower});
            if (lower < best_bound) best_bound = lower, best_block = blocks.size() - 1;
            n_left += entering;
            n_right -= leaving;
            i = j;
        }
        Split best;
        if (!(best_bound < bound)) return best;
        {
            const SweepBlock& b = blocks[best_block];
            best = sweep(s, ev, b.begin, b.end, b.n_left, b.n_right);
        }
        for (size_t k = 0; k < blocks.size(); ++k) {
            const SweepBlock& b = blocks[k];
            if (k == best_block || !(b.bound < bound) || b.bound > best.cost) continue;
            const Split r = sweep(s, ev, b.begin, b.end, b.n_left, b.n_right);
            if (r.cost < best.cost || (r.cost == best.cost && k < best_block)) {
                best = r;
                best_block = k;
            }
        }
        return best;
    }

    /// Whether sweep_pruned's bounds hold: SahCost::split monotone in the probabilities and
    /// counts (non-negative, finite factors).
    bool prunable() const noexcept {
        return cost_.c_isect >= 0 && cost_.empty_scale >= 0 && std::isfinite(cost_.c_isect) &&
               std::isfinite(cost_.empty_scale) && std::isfinite(cost_.c_trav);
    }

    Split find_split(const NodeInput& in, Scratch& scratch) const {
        std::array<Split, 3> per_axis;
        const double area = half_area(in.cell);
        if (!(area > 0)) return {};  // no area: nothing to split
        const double inv_area = 1.0 / area;
        auto sweep_axis = [&](int a) {
            if (!(in.cell.lo[a] < in.cell.hi[a])) return;  // flat along this axis: nothing to split
            const SweepSetup s = sweep_setup(in, a, inv_area);
            per_axis[a] = in.count[a] >= kParallelAxes
                              ? sweep_parallel(s, in.events(a), in.count[a])
                              : sweep(s, in.events(a), 0, in.count[a], 0, in.prim_count);
        };
        if (prune_ && prunable() && std::isfinite(inv_area)) {
            // A candidate is chosen only if it costs less than the leaf and than every lower
            // axis' best (which wins ties).
            double bound = cost_.leaf(in.prim_count);
            for (int a = 0; a < 3; ++a) {
                if (!(in.cell.lo[a] < in.cell.hi[a])) continue;
                const SweepSetup s = sweep_setup(in, a, inv_area);
                // The bounds need non-negative, finite probabilities' factors (a valid cell).
                const bool prune = in.count[a] >= kPruneFrom && s.cap >= 0 && s.ring >= 0 &&
                                   std::isfinite(s.cap) && std::isfinite(s.ring);
                per_axis[a] =
                    prune ? sweep_pruned(s, in.events(a), in.count[a], bound, scratch.blocks)
                          : sweep(s, in.events(a), 0, in.count[a], 0, in.prim_count);
                bound = std::min(bound, per_axis[a].cost);
            }
        } else if (std::max({in.count[0], in.count[1], in.count[2]}) >= kParallelAxes) {
            tbb::this_task_arena::isolate([&] {
                tbb::parallel_invoke([&] { sweep_axis(0); }, [&] { sweep_axis(1); },
                                     [&] { sweep_axis(2); });
            });
        } else {
            for (int a = 0; a < 3; ++a) sweep_axis(a);
        }
        Split best = per_axis[0];
        for (int a = 1; a < 3; ++a)
            if (per_axis[a].cost < best.cost) best = per_axis[a];  // ties keep the lower axis
        return best;
    }

    /// Which child of `split` holds no triangle (0 left, 1 right), or -1 if both hold some,
    /// read from the ends of the split axis' sorted list. Events at the plane go left if they
    /// are ends or (planar_left) planars, right if starts or (!planar_left) planars: so the
    /// events below `first_right` (the plane's key with the first type that goes right) are
    /// exactly those that put their triangle on the left.
    static int empty_side(const NodeInput& in, const Split& split) noexcept {
        const Event* ev = in.events(split.axis);
        const size_t n = in.count[split.axis];
        if (n == 0) return -1;
        const Event first_right = (Event{ordered_bits(split.pos)} << 32) |
                                  (Event{split.planar_left ? kStart : kPlanar} << 30);
        if (ev[0] >= first_right) return 0;
        if (ev[n - 1] < first_right) return 1;
        return -1;
    }

    static const std::vector<uint32_t>& leaf_prims(const NodeInput& in,
                                                   std::vector<uint32_t>& prims) {
        prims.clear();
        const Event* ev = in.events(0);
        for (size_t i = 0; i < in.count[0]; ++i)
            if (event_type(ev[i]) != kEnd) prims.push_back(event_prim(ev[i]));
        std::sort(prims.begin(), prims.end());
        return prims;
    }

    /// Sets side[] for every triangle of the node and lists the straddling ones. The split axis'
    /// list is sorted, so it is three runs: positions left of the plane, on it, and right of it.
    /// Returns the number of triangles only on the left / only on the right.
    [[gnu::noinline]] static std::array<uint32_t, 2> classify(const NodeInput& in,
                                                              const Split& split, Side* side,
                                                              std::vector<uint32_t>& straddling,
                                                              const TriVerts* tris) {
        const Event* ev = in.events(split.axis);
        const size_t n = in.count[split.axis];
        const uint32_t plane = ordered_bits(split.pos);
        const Side planar_side = split.planar_left ? kLeftOnly : kRightOnly;
        uint32_t left_only = 0, right_only = 0;
        // Events below `on_plane` are left of the plane, those below `right` on it. ev[n] is
        // kSentinel, above both: the first two runs need no index check.
        const Event on_plane = Event{plane} << 32, right = (Event{plane} + 1) << 32;
        size_t i = 0;
        // Left of the plane: ends and planars are left only; a start is "both" until its end is
        // seen left of or on the plane.
        for (; ev[i] < on_plane; ++i) {
            const bool start = event_type(ev[i]) == kStart;
            side[event_prim(ev[i])] = start ? kBoth : kLeftOnly;
            left_only += start ? 0 : 1;
        }
        // On the plane: ends are left, starts right, planars where the split put them.
        for (; ev[i] < right; ++i) {
            const uint32_t type = event_type(ev[i]);
            const Side s = type == kEnd ? kLeftOnly : (type == kStart ? kRightOnly : planar_side);
            side[event_prim(ev[i])] = s;
            left_only += s.left;
            right_only += s.right;
        }
        // Right of the plane: starts and planars are right only; an end whose start was left of
        // the plane marks a straddling triangle.
        for (; i < n; ++i) {
            const uint32_t prim = event_prim(ev[i]);
            const bool end = event_type(ev[i]) == kEnd;
            const Side old = side[prim];
            side[prim] = end ? old : kRightOnly;
            right_only += end ? 0 : 1;
            if (end && (old.left | old.right) == 0) {  // kBoth, rare: predictable
                straddling.push_back(prim);
                // Its triangle is clipped soon: start loading it (36 bytes, up to two lines).
                __builtin_prefetch(&tris[prim]);
                __builtin_prefetch(reinterpret_cast<const char*>(&tris[prim]) + sizeof(TriVerts) -
                                   1);
            }
        }
        return {left_only, right_only};
    }

    /// Copies the events of ev[0, n) to l / r as `side` says, merging in the
    /// sorted, sentinel-terminated new events nl / nr. Returns the end pointers of l and r.
    /// Branch-free except for the (rare) merge steps; writes one slot past the end of each output.
    /// (sweep, classify and distribute are kept out of line: the hot loops get the registers to
    /// themselves, and profiles show them apart.)
    [[gnu::noinline]] static std::pair<Event*, Event*> distribute(const Event* ev, size_t n,
                                                                  const Side* side,
                                                                  const Event*& nl,
                                                                  const Event*& nr, Event* l,
                                                                  Event* r) {
        // Runs of events below the next new event need no merge step: one compare per event.
        // ev[n] is kSentinel, which no run passes.
        const Event* const end = ev + n;
        while (ev < end) {
            while (*nl < *ev) *l++ = *nl++;
            while (*nr < *ev) *r++ = *nr++;
            const Event next_new = std::min(*nl, *nr);
            Event e = *ev;
            do {
                const Side& s = side[event_prim(e)];
                *l = e;
                *r = e;
                l += s.left;
                r += s.right;
                e = *++ev;
            } while (e < next_new);
        }
        return {l, r};
    }

    /// Classifies the triangles against the split and builds the children's sorted event lists.
    void partition(const NodeInput& in, const Split& split, NodeInput& left, NodeInput& right,
                   Scratch& scratch) {
        const int k = split.axis;
        const float p = split.pos;
        left.cell = in.cell;
        right.cell = in.cell;
        left.cell.hi[k] = p;
        right.cell.lo[k] = p;
        left.depth = right.depth = in.depth + 1;

        // The scratch memory is per thread; it is used only inside this call, whose parallel part
        // is isolated so no other node's work can run on this thread in between.
        Side* side = scratch.side.get();
        std::vector<uint32_t>& straddling = scratch.straddling;
        straddling.clear();
        auto [left_only, right_only] = classify(in, split, side, straddling, tris_.data());

        // Straddling triangles are clipped to each child ("perfect splits"); their new events are
        // few (O(sqrt N) on typical meshes), sorted here and merged into the filtered lists.
        NewEvents& new_left = scratch.new_left;
        NewEvents& new_right = scratch.new_right;
        new_left.reset(straddling.size());
        new_right.reset(straddling.size());
        for (uint32_t prim : straddling) {
            Aabb left_box, right_box;
            bool left_ok = false, right_ok = false;
            clip_to_children(tris_[prim], left.cell, right.cell, k, left_ok, left_box, right_ok,
                             right_box);
            if (left_ok) {
                new_left.add(left_box, prim);
                ++left_only;
            }
            if (right_ok) {
                new_right.add(right_box, prim);
                ++right_only;
            }
        }
        left.prim_count = left_only;
        right.prim_count = right_only;
        new_left.finish();
        new_right.finish();

        // At most two events per triangle on each axis (prim_count includes the straddlers), plus
        // the one slot distribute() writes past the end.
        const size_t stride_l = 2 * size_t{left.prim_count} + 1,
                     stride_r = 2 * size_t{right.prim_count} + 1;
        left.buffer = scratch.take(3 * stride_l);
        right.buffer = scratch.take(3 * stride_r);
        for (int a = 0; a < 3; ++a) left.offset[a] = a * stride_l, right.offset[a] = a * stride_r;

        auto split_axis = [&](int a) {
            Event* l0 = left.buffer.data.get() + left.offset[a];
            Event* r0 = right.buffer.data.get() + right.offset[a];
            const Event* nl = new_left.list[a].data();
            const Event* nr = new_right.list[a].data();
            auto [l, r] = distribute(in.events(a), in.count[a], side, nl, nr, l0, r0);
            while (*nl != kSentinel) *l++ = *nl++;
            while (*nr != kSentinel) *r++ = *nr++;
            *l = kSentinel;  // ends the list for sweep()
            *r = kSentinel;
            left.count[a] = static_cast<size_t>(l - l0);
            right.count[a] = static_cast<size_t>(r - r0);
        };
        if (in.count[k] >= kParallelAxes) {
            tbb::this_task_arena::isolate([&] {
                tbb::parallel_invoke([&] { split_axis(0); }, [&] { split_axis(1); },
                                     [&] { split_axis(2); });
            });
        } else {
            for (int a = 0; a < 3; ++a) split_axis(a);
        }
    }

    std::span<const TriVerts> tris_;
    SahCost cost_;
    bool empty_cuts_in_place_;
    bool prune_;
    uint32_t max_depth_;
    tbb::enumerable_thread_specific<Scratch> scratch_;
};

/// Sorts the root's events of one axis, ev[0, n), in place. The events were created in triangle
/// order, so a stable sort on the position and type bits alone (a least-significant-digit radix
/// sort in three passes of 11, 11 and 12 bits) gives exactly the order of sorting the 64-bit
/// integers. `temp`: room for n events.
void radix_sort_events(Event* ev, size_t n, Event* temp) {
    constexpr int kShift[3] = {30, 41, 52};
    constexpr int kBits[3] = {11, 11, 12};
    std::vector<uint32_t> histogram[3];
    for (int p = 0; p < 3; ++p) histogram[p].assign(size_t{1} << kBits[p], 0);
    for (size_t i = 0; i < n; ++i)
        for (int p = 0; p < 3; ++p)
            ++histogram[p][(ev[i] >> kShift[p]) & ((uint64_t{1} << kBits[p]) - 1)];
    // Passes: ev -> temp -> ev -> temp, then back (each writes all n events before the next
    // reads them).
    Event* src = ev;
    Event* dst = temp;
    for (int p = 0; p < 3; ++p) {
        uint32_t sum = 0;
        for (uint32_t& h : histogram[p]) {
            const uint32_t c = h;
            h = sum;
            sum += c;
        }
        const uint64_t mask = (uint64_t{1} << kBits[p]) - 1;
        for (size_t i = 0; i < n; ++i) {
            const Event e = src[i];
            dst[histogram[p][(e >> kShift[p]) & mask]++] = e;
        }
        std::swap(src, dst);
    }
    std::memcpy(ev, src, n * sizeof(Event));
}

}  // namespace

struct ExactSahBuilder::Impl {
    SahBuilder builder;
    std::span<const TriVerts> tris;
};

ExactSahBuilder::ExactSahBuilder(std::span<const TriVerts> tris, const BuildOptions& options,
                                 bool empty_cuts_in_place, bool prune_sweep)
    : impl_(std::make_unique<Impl>(
          Impl{SahBuilder(tris, options, empty_cuts_in_place, prune_sweep), tris})) {}

ExactSahBuilder::~ExactSahBuilder() = default;

void ExactSahBuilder::build(SubTree& out, uint32_t slot, const Aabb& cell,
                            std::span<const PrimBox> prims, uint32_t depth) {
    build_events(out, slot, cell, prims.size(), depth, [&](const auto& add) {
        for (const PrimBox& p : prims) add(p.box, p.prim);
    });
}

void ExactSahBuilder::build_all(SubTree& out, uint32_t slot, const Aabb& cell,
                                std::span<const uint8_t> skip, size_t count, uint32_t depth) {
    const std::span<const TriVerts> tris = impl_->tris;
    build_events(out, slot, cell, count, depth, [&](const auto& add) {
        size_t added = 0;
        for (size_t prim = 0; prim < tris.size() && added < count; ++prim) {
            Aabb box;
            if (skip[prim] || !vertex_bounds_in_cell(tris[prim], cell, box)) continue;
            add(box, static_cast<uint32_t>(prim));
            ++added;
        }
    });
}

template <typename EachPrim>
void ExactSahBuilder::build_events(SubTree& out, uint32_t slot, const Aabb& cell, size_t count,
                                   uint32_t depth, const EachPrim& each_prim) {
    // The node's events go straight into its buffer (at most two per triangle and axis, plus the
    // sentinel), in triangle order; each axis is then sorted.
    NodeInput in;
    in.cell = cell;
    in.depth = depth;
    const size_t stride = 2 * count + 1;
    in.buffer = impl_->builder.take_buffer(3 * stride);
    for (int a = 0; a < 3; ++a) in.offset[a] = a * stride;
    Event* const ev = in.buffer.data.get();
    each_prim([&](const Aabb& box, uint32_t prim) {
        for (int a = 0; a < 3; ++a) {
            Event* dst = ev + in.offset[a] + in.count[a];
            if (box.lo[a] == box.hi[a]) {
                dst[0] = make_event(box.lo[a], kPlanar, prim);
                in.count[a] += 1;
            } else {
                dst[0] = make_event(box.lo[a], kStart, prim);
                dst[1] = make_event(box.hi[a], kEnd, prim);
                in.count[a] += 2;
            }
        }
    });
    in.prim_count = static_cast<uint32_t>(count);
    // A big root's axes, sorted concurrently, share one scratch buffer, each in its own part:
    // one tree-memory mapping, which, freed right after the sorts, is kept for the build
    // (RecycleTreeMappings) and serves the first partitions' children. Three buffers of their
    // own were each just under a huge page (the stadium: 3 x 2.06 MB), heap blocks the heap gave
    // back to the kernel: ~4 MB of fresh pages a first build that nothing else reused.
    const size_t all_events = in.count[0] + in.count[1] + in.count[2];
    EventBuffer shared;
    if (count >= kParallelSubtrees && all_events >= kHugePageEvents)
        shared = impl_->builder.take_buffer(all_events);
    auto sort_axis = [&](int a) {
        Event* first = ev + in.offset[a];
        // Both give the order of the 64-bit integers; the radix sort (stable, prims ascending)
        // only pays on long lists.
        if (in.count[a] >= kRadixSortEvents) {
            if (shared.data) {
                Event* const part =
                    shared.data.get() + (a > 0 ? in.count[0] : 0) + (a > 1 ? in.count[1] : 0);
                radix_sort_events(first, in.count[a], part);
            } else {
                EventBuffer temp = impl_->builder.take_buffer(in.count[a]);
                radix_sort_events(first, in.count[a], temp.data.get());
                impl_->builder.give_buffer(std::move(temp));
            }
        } else {
            std::sort(first, first + in.count[a]);
        }
        first[in.count[a]] = kSentinel;
    };
    if (count >= kParallelSubtrees) {
        tbb::this_task_arena::isolate([&] {
            tbb::parallel_invoke([&] { sort_axis(0); }, [&] { sort_axis(1); },
                                 [&] { sort_axis(2); });
        });
    } else {
        for (int a = 0; a < 3; ++a) sort_axis(a);
    }
    if (shared.data) impl_->builder.give_buffer(std::move(shared));
    impl_->builder.build_root(out, slot, std::move(in));
}

bool clip_to_cell(const TriVerts& tri, const Aabb& cell, Aabb& out) {
    return clipped_bounds(tri, cell, out) || vertex_bounds_in_cell(tri, cell, out);
}

void clip_to_children(const TriVerts& tri, const Aabb& left, const Aabb& right, int axis,
                      bool& left_ok, Aabb& left_box, bool& right_ok, Aabb& right_box) {
    clipped_bounds_in_children(tri, left, right, axis, left_ok, left_box, right_ok, right_box);
    left_ok = left_ok || vertex_bounds_in_cell(tri, left, left_box);
    right_ok = right_ok || vertex_bounds_in_cell(tri, right, right_box);
}

bool misses_cell(const TriVerts& tri, const Aabb& cell) {
    // Grown by 2^-20 of the cell's size or position, whichever is larger: far more than the
    // clipping's rounding, so a triangle that touches the cell is never reported as missing it.
    Aabb grown = cell;
    for (int a = 0; a < 3; ++a) {
        const float margin =
            std::max({std::fabs(cell.lo[a]), std::fabs(cell.hi[a]), cell.hi[a] - cell.lo[a]}) *
            0x1p-20f;
        grown.lo[a] -= margin;
        grown.hi[a] += margin;
    }
    Aabb unused;
    return !clipped_bounds(tri, grown, unused);
}

bool clip_unless_missing(const TriVerts& tri, const Aabb& cell, Aabb& out) {
    if (clipped_bounds(tri, cell, out)) return true;
    return !misses_cell(tri, cell) && vertex_bounds_in_cell(tri, cell, out);
}

}  // namespace kdrt::detail
