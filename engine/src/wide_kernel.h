#pragma once
// Internal: the single-ray kernel over wide nodes (issue 23). One step decodes a 3-level treelet
// (WideNode): the seven plane crossings in one 8-lane operation, each of the eight slots' cell
// interval from its three ancestors' crossings through fixed shuffles, the slots' front-to-back
// order from the ray's near sides through a table (exact for a kD-tree: the cells do not
// overlap). Written with GCC vector extensions only, so every translation unit compiles it for its
// own instruction set (two SSE2 operations per 8-lane one at the baseline, one on AVX2).
//
// Per slot the kernel makes exactly the binary kernel's decisions (Stoll 2005, as the packet
// kernels make them per lane): at a plane with crossing t and tolerance eps, near is needed
// unless t + eps < tmin, far unless t - eps > tmax; only when both are needed is near's tmax cut
// to t + eps and far's tmin raised to t - eps; a NaN crossing (a ray in the plane) needs both with
// unchanged intervals. Cells come off the stack front to back, and those that start beyond the
// closest hit are skipped (as the packet kernels skip them lane by lane). So a ray visits the
// leaves and tests the triangles the binary traversal would, in the same order, and the work
// counters (Count) count the binary kernel's steps as well as the wide nodes.
//
// Everything is in an anonymous namespace and `static inline` (see ray_prep.h): each translation
// unit keeps its own copy for its own target. A unit compiled for AVX2 or later defines
// KDRT_WIDE_AVX2 before including this (a target pragma does not set __AVX2__), for the 8-lane
// permutes and movemask; one compiled for AVX-512 (F, VL, DQ) defines KDRT_WIDE_AVX512 as well,
// for the decode's masked levels and compaction by vpcompress.

#include <immintrin.h>

#include <cstddef>
#include <cstdint>

#include "kdrt/kdtree.h"
#include "packet.h"
#include "ray_prep.h"

// The 8-lane helpers take and return 32-byte vectors; at the baseline (no AVX) GCC warns that such
// a function's ABI differs between targets. They have internal linkage and are inlined, so no
// call crosses targets. (GCC reports it where a template is instantiated, so the setting stays on
// for the rest of the including translation unit.)
#pragma GCC diagnostic ignored "-Wpsabi"

namespace kdrt::detail {
namespace {

namespace wide {

using F8 = float __attribute__((vector_size(32)));
using I8 = int32_t __attribute__((vector_size(32)));
using U8 = uint32_t __attribute__((vector_size(32)));

/// order[nh] packs the front-to-back slot order of a treelet, 3 bits a position (position p in
/// bits 3p..3p+2), for the near sides nh (bit j set: plane j's near side is its high side).
/// Position p = 4 c0 + 2 c1 + c2 with c = 0 for the near side, 1 for the far side at each level.
struct OrderTable {
    uint32_t order[128];
    constexpr OrderTable() : order{} {
        for (uint32_t nh = 0; nh < 128; ++nh) {
            uint32_t packed = 0;
            for (uint32_t p = 0; p < 8; ++p) {
                const uint32_t b0 = ((p >> 2) & 1u) ^ (nh & 1u);
                const uint32_t b1 = ((p >> 1) & 1u) ^ ((nh >> (1 + b0)) & 1u);
                const uint32_t b2 = (p & 1u) ^ ((nh >> (3 + 2 * b0 + b1)) & 1u);
                packed |= (4 * b0 + 2 * b1 + b2) << (3 * p);
            }
            order[nh] = packed;
        }
    }
};
inline constexpr OrderTable kOrder{};

/// The same orders one byte a position (position p in byte p): permute indices for AVX2.
struct OrderBytes {
    uint64_t order[128];
    constexpr OrderBytes() : order{} {
        for (uint32_t nh = 0; nh < 128; ++nh)
            for (uint32_t p = 0; p < 8; ++p)
                order[nh] |= static_cast<uint64_t>((kOrder.order[nh] >> (3 * p)) & 7u) << (8 * p);
    }
};
inline constexpr OrderBytes kOrderBytes{};

/// The orders reversed, farthest first (byte j: the slot s at position 7 - j): a decode pushes
/// its cells farthest first, so the nearest ends on top of the stack. With each slot's ancestor
/// planes at levels 1 and 2 (byte j: 1 + (s >> 2) and 3 + (s >> 1)), so that a decode reads its
/// three permutes' indices from one entry.
struct FarFirstBytes {
    struct Entry {
        uint64_t order, plane1, plane2;
    };
    Entry entry[128];
    constexpr FarFirstBytes() : entry{} {
        for (uint32_t nh = 0; nh < 128; ++nh)
            for (uint32_t j = 0; j < 8; ++j) {
                const uint32_t s = (kOrder.order[nh] >> (3 * (7 - j))) & 7u;
                entry[nh].order |= static_cast<uint64_t>(s) << (8 * j);
                entry[nh].plane1 |= static_cast<uint64_t>(1 + (s >> 2)) << (8 * j);
                entry[nh].plane2 |= static_cast<uint64_t>(3 + (s >> 1)) << (8 * j);
            }
    }
};
inline constexpr FarFirstBytes kFarFirstBytes{};

/// index[m] packs the lanes set in the 8-bit mask m, in increasing order, one byte each: a
/// permute by it moves the chosen lanes to the front, so one whole-vector store pushes them.
struct CompactBytes {
    uint64_t index[256];
    constexpr CompactBytes() : index{} {
        for (uint32_t m = 0; m < 256; ++m) {
            uint32_t k = 0;
            for (uint32_t lane = 0; lane < 8; ++lane)
                if (m & (1u << lane)) index[m] |= static_cast<uint64_t>(lane) << (8 * k++);
        }
    }
};
inline constexpr CompactBytes kCompactBytes{};

/// The slots of `valid` (bit s for slot s) as positions (bit p for position p): each level's
/// near sides swap the halves below their plane. Branch-free.
static inline uint32_t positions(uint32_t valid, uint32_t nh) {
    // Level 2: plane 3 + k decides slots 2k and 2k + 1.
    const uint32_t n2 = (nh >> 3) & 15u;
    const uint32_t s2 =
        (n2 & 1u) * 0x03u | (n2 & 2u) * 0x06u | (n2 & 4u) * 0x0Cu | (n2 & 8u) * 0x18u;
    uint32_t v = (valid & ~s2) | ((valid & s2 & 0x55u) << 1) | ((valid & s2 & 0xAAu) >> 1);
    // Level 1: plane 1 decides slots 0..3, plane 2 slots 4..7.
    const uint32_t s1 = ((nh >> 1) & 1u) * 0x0Fu | ((nh >> 2) & 1u) * 0xF0u;
    v = (v & ~s1) | ((v & s1 & 0x33u) << 2) | ((v & s1 & 0xCCu) >> 2);
    // Level 0.
    const uint32_t s0 = (nh & 1u) * 0xFFu;
    return (v & ~s0) | (((v << 4) | (v >> 4)) & s0 & 0xFFu);
}

/// One bit per lane of an 8-lane mask (bit i set when lane i is true).
static inline uint32_t bits8(I8 m) {
#if defined(KDRT_WIDE_AVX2)
    return static_cast<uint32_t>(_mm256_movemask_ps(reinterpret_cast<__m256>(m)));
#else
    using I4 = int32_t __attribute__((vector_size(16)));
    const I4 lo = __builtin_shufflevector(m, m, 0, 1, 2, 3);
    const I4 hi = __builtin_shufflevector(m, m, 4, 5, 6, 7);
    return static_cast<uint32_t>(_mm_movemask_ps(reinterpret_cast<__m128>(lo)) |
                                 (_mm_movemask_ps(reinterpret_cast<__m128>(hi)) << 4));
#endif
}

template <class V>
static inline V pick(I8 m, V a, V b) {
    return m ? a : b;
}

using F4 = float __attribute__((vector_size(16)));
using I4 = int32_t __attribute__((vector_size(16)));

/// One bit per lane of a 4-lane mask.
static inline uint32_t bits4(I4 m) {
    return static_cast<uint32_t>(_mm_movemask_ps(reinterpret_cast<__m128>(m)));
}

/// The 4x4 transpose: c0..c3 are the columns of the rows r[0..3].
static inline void transpose4(const F4 r[4], F4& c0, F4& c1, F4& c2, F4& c3) {
    const F4 lo01 = __builtin_shufflevector(r[0], r[1], 0, 4, 1, 5);
    const F4 lo23 = __builtin_shufflevector(r[2], r[3], 0, 4, 1, 5);
    const F4 hi01 = __builtin_shufflevector(r[0], r[1], 2, 6, 3, 7);
    const F4 hi23 = __builtin_shufflevector(r[2], r[3], 2, 6, 3, 7);
    c0 = __builtin_shufflevector(lo01, lo23, 0, 1, 4, 5);
    c1 = __builtin_shufflevector(lo01, lo23, 2, 3, 6, 7);
    c2 = __builtin_shufflevector(hi01, hi23, 0, 1, 4, 5);
    c3 = __builtin_shufflevector(hi01, hi23, 2, 3, 6, 7);
}

/// A leaf's triangles four at a time: one pass of the watertight test for one ray against four
/// triangles (a lane each), lane by lane the arithmetic of intersect_triangle (ray_prep.h), so each
/// lane's answer is the scalar test's bit for bit: the same subtractions, products and divisions
/// in the same order (no FMA: -ffp-contract=off), and the same double-precision retry of the edge
/// functions for the lanes where one is exactly zero. The triangles are read from the leaf-ordered
/// array as they are stored (no copy per leaf, so no bytes per triangle are added) and transposed
/// in registers. A short leaf repeats a triangle in the spare lanes (the same answer twice).
///
/// Returns the lanes hit at t >= tmin (t not NaN), with t, the edge functions v and w, and det
/// per lane (a hit's barycentrics are v / det and w / det, divided by the caller for the hit it
/// keeps, as intersect_triangle divides them).
template <class F>
struct LaneHits {
    F t, v, w, det;
};
using Hits4 = LaneHits<F4>;
using Hits8 = LaneHits<F8>;

static inline uint32_t lane_bits(I4 m) { return bits4(m); }
static inline uint32_t lane_bits(I8 m) { return bits8(m); }

/// The edge functions u, v, w of a pass, one triangle a lane.
template <class F>
struct EdgeLanes {
    F u, v, w;
};

/// intersect_triangle's double-precision retry of the edge functions for the lanes set in
/// `lanes` (where one came out exactly zero); the other lanes keep `e`. Rare (a ray through a
/// triangle's edge or vertex), so it is a call: the pass's hot path keeps its registers.
template <class F>
[[gnu::noinline, gnu::cold]] static EdgeLanes<F> exact_edge_lanes(F ax, F ay, F bx, F by, F cx,
                                                                  F cy, EdgeLanes<F> e,
                                                                  uint32_t lanes) {
    for (; lanes; lanes &= lanes - 1) {
        const int l = __builtin_ctz(lanes);
        float eu, ev, ew;
        exact_edges(ax[l], ay[l], bx[l], by[l], cx[l], cy[l], eu, ev, ew);
        e.u[l] = eu;
        e.v[l] = ev;
        e.w[l] = ew;
    }
    return e;
}

/// The test itself, one triangle a lane, on the triangles' coordinates as columns in the ray's
/// permuted frame: ray_axes[vertex][j] holds coordinate k_j (kx, ky, kz for j = 0, 1, 2) of every
/// lane's triangle. F is F4 or F8 (I its mask).
template <class F, class I>
[[gnu::always_inline]] static inline uint32_t intersect_ray_axes(const PreparedRay& p,
                                                                 const F (&ray_axes)[3][3],
                                                                 float tmin, LaneHits<F>& out) {
    const F ox = F{} + p.org[p.kx], oy = F{} + p.org[p.ky], oz = F{} + p.org[p.kz];
    const F a_x = ray_axes[0][0] - ox, a_y = ray_axes[0][1] - oy, a_z = ray_axes[0][2] - oz;
    const F b_x = ray_axes[1][0] - ox, b_y = ray_axes[1][1] - oy, b_z = ray_axes[1][2] - oz;
    const F c_x = ray_axes[2][0] - ox, c_y = ray_axes[2][1] - oy, c_z = ray_axes[2][2] - oz;
    const F sx = F{} + p.sx, sy = F{} + p.sy, sz = F{} + p.sz;
    const F ax = a_x - sx * a_z, ay = a_y - sy * a_z;
    const F bx = b_x - sx * b_z, by = b_y - sy * b_z;
    const F cx = c_x - sx * c_z, cy = c_y - sy * c_z;
    F u = cx * by - cy * bx;
    F v = ax * cy - ay * cx;
    F w = bx * ay - by * ax;
    const uint32_t zero_edge = lane_bits((u == 0.0f) | (v == 0.0f) | (w == 0.0f));
    if (__builtin_expect(zero_edge != 0, 0)) {
        // intersect_triangle's double-precision retry, out of line (the inputs go by value), so
        // that the pass keeps them in registers rather than on the stack for it.
        const EdgeLanes<F> e = exact_edge_lanes<F>(ax, ay, bx, by, cx, cy, {u, v, w}, zero_edge);
        u = e.u;
        v = e.v;
        w = e.w;
    }
    const I outside =
        ((u < 0.0f) | (v < 0.0f) | (w < 0.0f)) & ((u > 0.0f) | (v > 0.0f) | (w > 0.0f));
    const F det = u + v + w;
    const F az = sz * a_z, bz = sz * b_z, cz = sz * c_z;
    const F t_scaled = u * az + v * bz + w * cz;
    const F t = t_scaled / det;
    // t >= tmin also rejects NaN.
    const I hit = ~outside & (det != 0.0f) & (t >= tmin);
    out = {t, v, w, det};
    return lane_bits(hit);
}

/// The same test on the columns in the mesh's axes: coord[vertex][axis]. The ray's axes are picked
/// by index (the columns go through memory; for the four-lane passes).
template <class F, class I>
[[gnu::always_inline]] static inline uint32_t intersect_lanes(const PreparedRay& p,
                                                              const F (&coord)[3][3], float tmin,
                                                              LaneHits<F>& out) {
    const F ray_axes[3][3] = {{coord[0][p.kx], coord[0][p.ky], coord[0][p.kz]},
                              {coord[1][p.kx], coord[1][p.ky], coord[1][p.kz]},
                              {coord[2][p.kx], coord[2][p.ky], coord[2][p.kz]}};
    return intersect_ray_axes<F, I>(p, ray_axes, tmin, out);
}

[[gnu::always_inline]] static inline uint32_t intersect4(const PreparedRay& p,
                                                         const TriVerts* const tri[4], float tmin,
                                                         Hits4& out) {
    // Rows: floats 0..3 (v0 and v1's x) and 4..7 (v1's y, z and v2's x, y) of each triangle, and
    // float 8 (v2's z) on its own; the 16 bytes read stay inside the 36-byte triangle.
    F4 r0[4], r1[4];
    for (int i = 0; i < 4; ++i) {
        __builtin_memcpy(&r0[i], &tri[i]->v0[0], sizeof(F4));
        __builtin_memcpy(&r1[i], &tri[i]->v1[1], sizeof(F4));
    }
    // Columns: coord[vertex][axis], one lane per triangle.
    F4 coord[3][3];
    transpose4(r0, coord[0][0], coord[0][1], coord[0][2], coord[1][0]);
    transpose4(r1, coord[1][1], coord[1][2], coord[2][0], coord[2][1]);
    coord[2][2] = F4{tri[0]->v2[2], tri[1]->v2[2], tri[2]->v2[2], tri[3]->v2[2]};
    return intersect_lanes<F4, I4>(p, coord, tmin, out);
}

/// Eight triangles in one pass (the single-ray walk on AVX2 and later): intersect4's test in
/// eight lanes, so each lane's answer is the scalar test's bit for bit as well. A leaf's run of
/// up to eight references is one pass instead of two, and the loop over a leaf's blocks exits
/// (a branch the predictor mostly misses) half as often. Lane i tests tris[index[i]].
///
/// Everything stays in registers: each triangle's row (floats 0..7) is read straight from `tris`
/// by its index and put in the ray's axes by one permute (v0's and v1's coordinates k_x, k_y,
/// k_z; two of v2's), the rows are transposed in registers, and v2's coordinates are completed
/// from its z (read on its own) by blends with masks that are the same in every lane (intersect4
/// picks them by index, through memory). Picking is exact, so the values, and the answers, are
/// intersect4's.
#if defined(KDRT_WIDE_AVX2)
[[gnu::always_inline]] static inline uint32_t intersect8(const PreparedRay& p, const TriVerts* tris,
                                                         U8 index, float tmin, Hits8& out) {
    // The row's permute: lanes 0..5 are v0's and v1's coordinates in the ray's axes (float
    // 3 v + k_j); lanes 6 and 7 two of v2's, and column 8 (v2's z, not in the row) the third,
    // each in the place that leaves v2's picks below at one blend each for k_x and k_y and two
    // for k_z: where kz = 2, lanes 6, 7 hold v2's k_x, k_y; where kx = 2, v2's k_z, k_y; where
    // ky = 2, v2's k_x, k_z.
    const int kx = p.kx, ky = p.ky, kz = p.kz;
    const __m256i row_pick = _mm256_setr_epi32(kx, ky, kz, 3 + kx, 3 + ky, 3 + kz,
                                               6 + (kx == 2 ? kz : kx), 6 + (ky == 2 ? kz : ky));
    const I8 x_is_z = (I8{} + kx) == 2, y_is_z = (I8{} + ky) == 2, z_is_z = (I8{} + kz) == 2;
    // Each triangle's offset in floats (9 an index) in the vector, so that a row's address is
    // one addressing mode (base + 4 offset), not two more instructions a lane.
    static_assert(sizeof(TriVerts) == 9 * sizeof(float));
    static_assert(kMaxTriangles * 9 <= 0x7fffffffu,
                  "a triangle's float offset fits the gather's int32");
    const U8 floats = (index << 3) + index;
    const char* base = reinterpret_cast<const char*>(tris);
    F8 r[8];
#pragma GCC unroll 8
    for (int i = 0; i < 8; ++i) {
        const char* tri = base + static_cast<size_t>(floats[i]) * sizeof(float);
        __m256 row;
        __builtin_memcpy(&row, tri, sizeof row);
        r[i] = reinterpret_cast<F8>(_mm256_permutevar8x32_ps(row, row_pick));
    }
    const F8 v2z = reinterpret_cast<F8>(
        _mm256_i32gather_ps(reinterpret_cast<const float*>(base + offsetof(TriVerts, v2[2])),
                            reinterpret_cast<__m256i>(floats), sizeof(float)));
    F8 t[8], u[8];
    for (int i = 0; i < 8; i += 2) {
        t[i] = __builtin_shufflevector(r[i], r[i + 1], 0, 8, 1, 9, 4, 12, 5, 13);
        t[i + 1] = __builtin_shufflevector(r[i], r[i + 1], 2, 10, 3, 11, 6, 14, 7, 15);
    }
    for (int i = 0; i < 8; i += 4) {
        u[i] = __builtin_shufflevector(t[i], t[i + 2], 0, 1, 8, 9, 4, 5, 12, 13);
        u[i + 1] = __builtin_shufflevector(t[i], t[i + 2], 2, 3, 10, 11, 6, 7, 14, 15);
        u[i + 2] = __builtin_shufflevector(t[i + 1], t[i + 3], 0, 1, 8, 9, 4, 5, 12, 13);
        u[i + 3] = __builtin_shufflevector(t[i + 1], t[i + 3], 2, 3, 10, 11, 6, 7, 14, 15);
    }
    // Column j: lane j of every permuted row (u[0..3] hold rows 0..3, u[4..7] rows 4..7).
    F8 col[9];
    for (int j = 0; j < 4; ++j) {
        col[j] = __builtin_shufflevector(u[j], u[j + 4], 0, 1, 2, 3, 8, 9, 10, 11);
        col[j + 4] = __builtin_shufflevector(u[j], u[j + 4], 4, 5, 6, 7, 12, 13, 14, 15);
    }
    col[8] = v2z;
    const F8 ray_axes[3][3] = {{col[0], col[1], col[2]},
                               {col[3], col[4], col[5]},
                               {pick(x_is_z, col[8], col[6]), pick(y_is_z, col[8], col[7]),
                                pick(z_is_z, col[8], pick(x_is_z, col[6], col[7]))}};
    return intersect_ray_axes<F8, I8>(p, ray_axes, tmin, out);
}
#endif

/// A ray's per-axis values: as 8-lane broadcasts (org[a], ...), and the three axes in lanes 0..2
/// (and again 4..6) of one vector each (xyz_org, ...) for a per-lane pick by permute.
struct Ray8 {
#if !defined(KDRT_WIDE_AVX2)
    F8 org[3], inv[3], eps[3];  // the 8-lane permute picks from xyz_* instead
#endif
    F8 xyz_org, xyz_inv, xyz_eps;  ///< lanes 0..2 and again 4..6; lanes 3 and 7 zero
};

/// One cell to visit: a slot word of WideNode (tag and index) with the ray's interval there.
/// `steps`: the binary kernel's inner nodes this cell's visit stands for (counting kernels only).
struct Cell {
    uint32_t slot;
    float tmin, tmax;
    uint32_t steps;
};

/// Stack depth: a path crosses at most kMaxDepth / 3 + 1 wide nodes, each leaving at most seven
/// cells behind.
inline constexpr int kStackCells = 7 * (kMaxDepth / 3 + 1) + 1;

/// The cells still to visit, the nearest on top, one array per field so that a decode pushes its
/// cells with whole-vector stores (+8: those stores write eight lanes whatever the count).
/// `steps` is written and read by the counting kernels only.
struct Stack {
    uint32_t slot[kStackCells + 8];
    float tmin[kStackCells + 8], tmax[kStackCells + 8];
    uint32_t steps[kStackCells + 8];

    [[nodiscard]] Cell at(int i, bool counts) const noexcept {
        return {slot[i], tmin[i], tmax[i], counts ? steps[i] : 0u};
    }
};

/// Decodes wide node `w` for a ray whose interval in its cell is [tmin, tmax]: pushes the slots
/// to visit onto `st` at `top`, back to front (the nearest last), and returns how many.
/// CountEmpty: empty leaves are visited too (the counting kernels count them as the binary
/// kernel does).
template <bool CountEmpty, bool CountSteps>
static inline int decode(const WideNode& w, const Ray8& r, float tmin, float tmax, Stack& st,
                         int top) {
    F8 split;
    __builtin_memcpy(&split, &w, sizeof split);
    const I8 lane = {0, 1, 2, 3, 4, 5, 6, 7};
    split = pick(lane < 7, split, F8{});  // lane 7 holds the axis bits
    // Each lane's plane axis (lane 7's code is 0, x: its split is 0 and its answers unused).
#if defined(KDRT_WIDE_AVX2)
    // The permute reads an index's low three bits: above a lane's code (bits 0..1) bit 2 is
    // the next plane's, and the ray's vectors hold their three axes twice (lanes 0..2 and
    // 4..6), so no mask is needed, and none delays the picks.
    const __m256i code = _mm256_srlv_epi32(_mm256_set1_epi32(static_cast<int>(w.axes)),
                                           _mm256_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14));
    const auto by_axis = [code](F8 xyz) {
        return reinterpret_cast<F8>(_mm256_permutevar8x32_ps(reinterpret_cast<__m256>(xyz), code));
    };
    const F8 org = by_axis(r.xyz_org), inv = by_axis(r.xyz_inv), eps = by_axis(r.xyz_eps);
#else
    const U8 axes =
        (U8{} + w.axes) & U8{3u, 3u << 2, 3u << 4, 3u << 6, 3u << 8, 3u << 10, 3u << 12, 0};
    const I8 is_x = reinterpret_cast<I8>(axes == 0u);
    const I8 is_y = reinterpret_cast<I8>(
        axes == U8{1u, 1u << 2, 1u << 4, 1u << 6, 1u << 8, 1u << 10, 1u << 12, 1u << 14});
    const F8 org = pick(is_x, r.org[0], pick(is_y, r.org[1], r.org[2]));
    const F8 inv = pick(is_x, r.inv[0], pick(is_y, r.inv[1], r.inv[2]));
    const F8 eps = pick(is_x, r.eps[0], pick(is_y, r.eps[1], r.eps[2]));
#endif
    const F8 t = (split - org) * inv;
    const F8 near_max = t + eps, far_min = t - eps;
#if defined(KDRT_WIDE_AVX2)
    // The near side is the high side where the reciprocal's sign bit is set (-0 and -inf
    // included): one movemask of the sign bits, and the sign bits themselves as the blend masks.
    const uint32_t nh =
        static_cast<uint32_t>(_mm256_movemask_ps(reinterpret_cast<__m256>(inv))) & 0x7Fu;
#else
    const I8 near_high = reinterpret_cast<I8>(inv) < 0;  // the sign bit, -0 and -inf included
    const uint32_t nh = bits8(near_high) & 0x7Fu;
#endif

    // Each level: lane s takes its ancestor plane's crossing and whether it lies on that plane's
    // far side (its side bit differs from the plane's near side). The far side's tmin is raised to
    // t - eps, the near side's tmax cut to t + eps, always: where the binary kernel leaves an
    // interval alone (only one side needed) the cut is a no-op, since t - eps > tmax (or
    // t + eps < tmin) there; a NaN crossing changes nothing. A slot is visited when its interval
    // is not empty, which holds exactly when each level needed its side.
#if defined(KDRT_WIDE_AVX2)
    if constexpr (!CountEmpty && !CountSteps) {
        // The walk's decode, computed in the ray's far-first order from the start: lane j holds
        // the slot at front-to-back position q = 7 - j = 4 c0 + 2 c1 + c2 (kFarFirstBytes). There,
        // a lane lies on the far side of its plane at level d exactly when c_d is 1, whatever
        // the ray's near sides: a constant blend per level. Only which plane a lane
        // takes at levels 1 and 2 depends on them (1 + (slot >> 2) and 3 + (slot >> 1), in the same
        // table entry), and that
        // is known as soon as the near sides are, beside the crossings' arithmetic. So the
        // intervals need no permute into stack order after the levels: the path from a node's
        // load to its nearest child's is one permute shorter, and the far sides' masks cost
        // nothing. The same operations on the same values lane by lane as below, so the same
        // answers.
        const FarFirstBytes::Entry& ff = kFarFirstBytes.entry[nh];
        const __m256i far_first =
            _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(static_cast<long long>(ff.order)));
        const __m256i plane1 =
            _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(static_cast<long long>(ff.plane1)));
        const __m256i plane2 =
            _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(static_cast<long long>(ff.plane2)));
        const __m256 nm_v = reinterpret_cast<__m256>(near_max);
        const __m256 fm_v = reinterpret_cast<__m256>(far_min);
        __m256 l = _mm256_set1_ps(tmin), h = _mm256_set1_ps(tmax);
        // Far lanes: level 0 {0..3}, level 1 {0, 1, 4, 5}, level 2 {0, 2, 4, 6}.
#if defined(KDRT_WIDE_AVX512)
#define KDRT_WIDE_FF_LEVEL(nm, fm, far)                                    \
    {                                                                      \
        l = _mm256_mask_max_ps(l, (far), (fm), l);                         \
        h = _mm256_mask_min_ps(h, static_cast<__mmask8>(~(far)), (nm), h); \
    }
#else
#define KDRT_WIDE_FF_LEVEL(nm, fm, far)                        \
    {                                                          \
        l = _mm256_blend_ps(l, _mm256_max_ps((fm), l), (far)); \
        h = _mm256_blend_ps(_mm256_min_ps((nm), h), h, (far)); \
    }
#endif
        KDRT_WIDE_FF_LEVEL(_mm256_permutevar8x32_ps(nm_v, _mm256_setzero_si256()),
                           _mm256_permutevar8x32_ps(fm_v, _mm256_setzero_si256()), 0x0F)
        KDRT_WIDE_FF_LEVEL(_mm256_permutevar8x32_ps(nm_v, plane1),
                           _mm256_permutevar8x32_ps(fm_v, plane1), 0x33)
        KDRT_WIDE_FF_LEVEL(_mm256_permutevar8x32_ps(nm_v, plane2),
                           _mm256_permutevar8x32_ps(fm_v, plane2), 0x55)
#undef KDRT_WIDE_FF_LEVEL
        __m256i slots;
        __builtin_memcpy(&slots, w.slot, sizeof slots);
        const __m256i slots_ff = _mm256_permutevar8x32_epi32(slots, far_first);
#if defined(KDRT_WIDE_AVX512)
        // lo <= hi (false for a NaN), and a tag with bit 1 set (a leaf or a node); the valid
        // cells compacted onto the stack by vpcompress.
        const __mmask8 mask = _mm256_cmp_ps_mask(l, h, _CMP_LE_OQ) &
                              _mm256_test_epi32_mask(slots_ff, _mm256_set1_epi32(2));
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(&st.slot[top]),
                            _mm256_maskz_compress_epi32(mask, slots_ff));
        _mm256_storeu_ps(&st.tmin[top], _mm256_maskz_compress_ps(mask, l));
        _mm256_storeu_ps(&st.tmax[top], _mm256_maskz_compress_ps(mask, h));
        return __builtin_popcount(static_cast<uint32_t>(mask));
#else
        const auto mask = bits8((reinterpret_cast<F8>(l) <= reinterpret_cast<F8>(h)) &
                                reinterpret_cast<I8>(reinterpret_cast<U8>(slots_ff) << 30));
        const __m256i compact = _mm256_cvtepu8_epi32(
            _mm_cvtsi64_si128(static_cast<long long>(kCompactBytes.index[mask])));
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(&st.slot[top]),
                            _mm256_permutevar8x32_epi32(slots_ff, compact));
        _mm256_storeu_ps(&st.tmin[top], _mm256_permutevar8x32_ps(l, compact));
        _mm256_storeu_ps(&st.tmax[top], _mm256_permutevar8x32_ps(h, compact));
        return __builtin_popcount(mask);
#endif
    }
#endif
    F8 lo = F8{} + tmin, hi = F8{} + tmax;
#if defined(KDRT_WIDE_AVX2)
    // Per level four operations on the intervals: max(fm, lo) is fm > lo ? fm : lo (lo where fm
    // is NaN), min(nm, hi) is nm < hi ? nm : hi, and a blend by the far side's sign bit (the
    // reciprocal's sign bit, flipped on the lanes below the plane's high side) keeps one of them.
    const I8 inv_bits = reinterpret_cast<I8>(inv);
#define KDRT_WIDE_LEVEL(i0, i1, i2, i3, i4, i5, i6, i7, side)                                      \
    {                                                                                              \
        const F8 nm = __builtin_shufflevector(near_max, near_max, i0, i1, i2, i3, i4, i5, i6, i7); \
        const F8 fm = __builtin_shufflevector(far_min, far_min, i0, i1, i2, i3, i4, i5, i6, i7);   \
        const __m256 far = reinterpret_cast<__m256>(                                               \
            __builtin_shufflevector(inv_bits, inv_bits, i0, i1, i2, i3, i4, i5, i6, i7) ^ (side)); \
        const __m256 l = reinterpret_cast<__m256>(lo), h = reinterpret_cast<__m256>(hi);           \
        lo = reinterpret_cast<F8>(                                                                 \
            _mm256_blendv_ps(l, _mm256_max_ps(reinterpret_cast<__m256>(fm), l), far));             \
        hi = reinterpret_cast<F8>(                                                                 \
            _mm256_blendv_ps(_mm256_min_ps(reinterpret_cast<__m256>(nm), h), h, far));             \
    }
#else
#define KDRT_WIDE_LEVEL(i0, i1, i2, i3, i4, i5, i6, i7, side)                                      \
    {                                                                                              \
        const F8 nm = __builtin_shufflevector(near_max, near_max, i0, i1, i2, i3, i4, i5, i6, i7); \
        const F8 fm = __builtin_shufflevector(far_min, far_min, i0, i1, i2, i3, i4, i5, i6, i7);   \
        const I8 far =                                                                             \
            __builtin_shufflevector(near_high, near_high, i0, i1, i2, i3, i4, i5, i6, i7) ^        \
            (side);                                                                                \
        lo = pick(far & (fm > lo), fm, lo);                                                        \
        hi = pick(~far & (nm < hi), nm, hi);                                                       \
    }
#endif
    KDRT_WIDE_LEVEL(0, 0, 0, 0, 0, 0, 0, 0, (I8{0, 0, 0, 0, -1, -1, -1, -1}))
    KDRT_WIDE_LEVEL(1, 1, 1, 1, 2, 2, 2, 2, (I8{0, 0, -1, -1, 0, 0, -1, -1}))
    KDRT_WIDE_LEVEL(3, 3, 4, 4, 5, 5, 6, 6, (I8{0, -1, 0, -1, 0, -1, 0, -1}))
#undef KDRT_WIDE_LEVEL
    I8 valid = lo <= hi;
    U8 slots;
    __builtin_memcpy(&slots, w.slot, sizeof slots);
    // From here on only each lane's sign bit of `valid` is read (movemask). A slot to visit is a
    // leaf or a node, the tags with bit 1 set: one shift moves it to the sign bit. The counting
    // kernels visit empty leaves too (any tag but kSlotNone).
    static_assert(WideNode::kSlotLeaf == 2 && WideNode::kSlotNode == 3 &&
                  WideNode::kSlotEmpty == 1 && WideNode::kSlotNone == 0);
    if constexpr (CountEmpty)
        valid &= reinterpret_cast<I8>((slots & 3u) != 0);
    else
        valid &= reinterpret_cast<I8>(slots << 30);
#if !defined(KDRT_WIDE_AVX2)
    if constexpr (!CountSteps) {
        // Branch-free: every slot written, farthest first, the top advanced past the valid ones.
        alignas(32) float lo_a[8], hi_a[8];
        __builtin_memcpy(lo_a, &lo, sizeof lo_a);
        __builtin_memcpy(hi_a, &hi, sizeof hi_a);
        const uint32_t valid_bits = bits8(valid);
        const uint32_t order = kOrder.order[nh];
        int n = 0;
        for (int p = 7; p >= 0; --p) {
            const uint32_t s = (order >> (3 * p)) & 7u;
            st.slot[top + n] = w.slot[s];
            st.tmin[top + n] = lo_a[s];
            st.tmax[top + n] = hi_a[s];
            n += static_cast<int>((valid_bits >> s) & 1u);
        }
        return n;
    }
#endif
    // The counting kernels: the cells in a loop, and each one's binary steps.
    int n = 0;
    uint32_t slot_of[8];
    Cell out[8];
#if defined(KDRT_WIDE_AVX2)
    // Everything into position order with one permute each; the valid positions in one movemask.
    const __m256i perm =
        _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(static_cast<long long>(kOrderBytes.order[nh])));
    const __m256i valid_p = _mm256_permutevar8x32_epi32(reinterpret_cast<__m256i>(valid), perm);
    uint32_t pos = static_cast<uint32_t>(_mm256_movemask_ps(_mm256_castsi256_ps(valid_p)));
    alignas(32) float lo_a[8], hi_a[8];
    alignas(32) uint32_t slot_a[8], index_a[8];
    _mm256_store_ps(lo_a, _mm256_permutevar8x32_ps(reinterpret_cast<__m256>(lo), perm));
    _mm256_store_ps(hi_a, _mm256_permutevar8x32_ps(reinterpret_cast<__m256>(hi), perm));
    _mm256_store_si256(reinterpret_cast<__m256i*>(slot_a),
                       _mm256_permutevar8x32_epi32(reinterpret_cast<__m256i>(slots), perm));
    if constexpr (CountSteps) _mm256_store_si256(reinterpret_cast<__m256i*>(index_a), perm);
    for (; pos; pos &= ~(0x80000000u >> __builtin_clz(pos))) {
        const auto p = static_cast<uint32_t>(31 - __builtin_clz(pos));
        if constexpr (CountSteps) slot_of[n] = index_a[p];
        out[n++] = {slot_a[p], lo_a[p], hi_a[p], 0};
    }
#else
    uint32_t pos = positions(bits8(valid), nh);
    alignas(32) float lo_a[8], hi_a[8];
    __builtin_memcpy(lo_a, &lo, sizeof lo_a);
    __builtin_memcpy(hi_a, &hi, sizeof hi_a);
    const uint32_t order = kOrder.order[nh];
    for (; pos; pos &= ~(0x80000000u >> __builtin_clz(pos))) {
        const auto p = static_cast<uint32_t>(31 - __builtin_clz(pos));
        const uint32_t s = (order >> (3 * p)) & 7u;
        slot_of[n] = s;
        out[n++] = {w.slot[s], lo_a[s], hi_a[s], 0};
    }
#endif
    if constexpr (CountSteps) {
        // A binary inner node is visited when the first cell below it is (the binary kernel
        // descends to it without a check): credit each real plane (not padding) to that cell.
        constexpr uint32_t kFirst[7] = {0, 0, 4, 0, 2, 4, 6}, kCount[7] = {8, 4, 4, 2, 2, 2, 2};
        for (int j = 0; j < WideNode::kPlanes; ++j) {
            if (!__builtin_isfinite(w.split[j])) continue;
            for (int c = n - 1; c >= 0; --c) {
                if (slot_of[c] >= kFirst[j] && slot_of[c] < kFirst[j] + kCount[j]) {
                    ++out[c].steps;
                    break;
                }
            }
        }
    }
    for (int c = 0; c < n; ++c) {
        st.slot[top + c] = out[c].slot;
        st.tmin[top + c] = out[c].tmin;
        st.tmax[top + c] = out[c].tmax;
        if constexpr (CountSteps) st.steps[top + c] = out[c].steps;
    }
    return n;
}

}  // namespace wide

/// Closest hit so far. Initialised to (ray.tmax, kNoHit) so a hit at exactly tmax still counts.
struct Best {
    float t;
    uint32_t prim;
    float u, v;
};

/// No counting: the public queries.
struct NoCount {
    static constexpr bool kCounts = false;
    void steps(uint32_t) noexcept {}
    void wide() noexcept {}
    void leaf(uint32_t) noexcept {}
};
/// Counting into TraceCounters: kdrt-bench trace --stats.
struct Count {
    static constexpr bool kCounts = true;
    TraceCounters& c;
    void steps(uint32_t n) noexcept { c.steps += n; }
    void wide() noexcept { ++c.wide_visits; }
    void leaf(uint32_t tris) noexcept {
        ++c.leaves;
        c.tri_tests += tris;
    }
};

/// One ray's walk through the wide nodes: its set-up, the cell it is in and the cells still to
/// visit, and its closest hit so far. The single-ray kernel runs one walk to its end
/// (traverse_wide); a batch of single rays advances several walks in turn (wide_step,
/// trace_in_turn), so one ray's loads overlap the others' work.
struct WideRay {
    PreparedRay p;
    wide::Ray8 r8;
    float ray_tmin, ray_tmax;
};
/// The arrays a walk reads, loaded once (the stack's stores could otherwise alias the vectors'
/// pointers, which would then be loaded again at every step).
struct WideArrays {
    const WideNode* wides;
    const uint32_t* refs;
    const TriVerts* tris;
    const uint32_t* ids;
    const uint32_t* refs_end;    ///< one past the last reference
    float bounds_mag;            ///< bounds_magnitude(tree.bounds), for traversal_eps
    float box_lo[4], box_hi[4];  ///< tree.bounds, lane 3 unused
    explicit WideArrays(const KdTree& tree) noexcept
        : wides(tree.wide_nodes.data()),
          refs(tree.leaf_refs.data()),
          tris(tree.tris.data()),
          ids(tree.tri_ids.data()),
          refs_end(tree.leaf_refs.data() + tree.leaf_refs.size()),
          bounds_mag(bounds_magnitude(tree.bounds)),
          box_lo{tree.bounds.lo[0], tree.bounds.lo[1], tree.bounds.lo[2], 0.0f},
          box_hi{tree.bounds.hi[0], tree.bounds.hi[1], tree.bounds.hi[2], 0.0f} {}
};

struct WideWalk {
    WideRay ray;
    wide::Cell cell;
    int stack_size;
    bool found;  ///< closest hit: a hit is kept in `best`; any hit: the ray is occluded
    Best best;
};

/// Sets `w` up for `ray` at the root, its closest hit so far (ray tmax, no hit). False when the ray
/// is invalid or misses the tree's box: then there is no hit, and nothing to walk. Checked: the
/// caller has already answered invalid rays and empty trees (octant_or_invalid) as misses.
template <bool Checked = false>
[[gnu::always_inline]] static inline bool wide_start(const KdTree& tree, const WideArrays& arrays,
                                                     const Ray& ray, WideRay& r,
                                                     wide::Cell& cell) noexcept {
    if constexpr (!Checked) {
        if (!ray_is_valid(ray) || tree.bounds.empty()) return false;
    }
    // prepare_ray, traversal_eps and clip_to_box with the three axes in the lanes of one SSE
    // vector (x86-64's baseline): lane by lane the same operations, so the same values; the
    // interval's maximum and minimum over the axes taken in clip_to_box's order (the sign of a
    // zero too). Lane 3 (the ray's tmin and tmax) is computed and never used.
    using wide::F4;
    F4 o, d, lo, hi;
    __builtin_memcpy(&o, &ray.ox, sizeof o);  // ox oy oz tmin
    __builtin_memcpy(&d, &ray.dx, sizeof d);  // dx dy dz tmax
    __builtin_memcpy(&lo, arrays.box_lo, sizeof lo);
    __builtin_memcpy(&hi, arrays.box_hi, sizeof hi);
    const F4 inv = 1.0f / d;  // +-inf for a zero component
    PreparedRay& p = r.p;
    __builtin_memcpy(p.org, &o, sizeof p.org);
    __builtin_memcpy(p.inv_dir, &inv, sizeof p.inv_dir);
    const float dir[3] = {d[0], d[1], d[2]};
    prepare_shear(dir, p);
    const F4 abs_o = reinterpret_cast<F4>(_mm_andnot_ps(_mm_set1_ps(-0.0f), o));
    const F4 abs_inv = reinterpret_cast<F4>(_mm_andnot_ps(_mm_set1_ps(-0.0f), inv));
    // interval_margin: the bounds' magnitude, then each origin coordinate's.
    float m = arrays.bounds_mag;
    m = abs_o[0] > m ? abs_o[0] : m;
    m = abs_o[1] > m ? abs_o[1] : m;
    m = abs_o[2] > m ? abs_o[2] : m;
    const float delta = m * 0x1p-20f;
    const wide::I4 is_inf = abs_inv == std::numeric_limits<float>::infinity();
    const F4 eps =
        reinterpret_cast<F4>(_mm_andnot_ps(reinterpret_cast<__m128>(is_inf), delta * abs_inv));
    // clip_to_box: an axis with an infinite reciprocal constrains nothing, or the ray misses.
    if (wide::bits4(is_inf & ((o < lo) | (o > hi))) & 7u) return false;
    const F4 t0 = (lo - o) * inv, t1 = (hi - o) * inv;
    constexpr float kInf = std::numeric_limits<float>::infinity();
    // Such an axis's lanes become -inf and +inf, which leave tmin and tmax as they are.
    const F4 near =
        is_inf ? F4{} - kInf : reinterpret_cast<F4>(_mm_min_ps(t1, t0)) - eps;  // t0 > t1 ? t1 : t0
    const F4 far =
        is_inf ? F4{} + kInf : reinterpret_cast<F4>(_mm_max_ps(t0, t1)) + eps;  // t0 > t1 ? t0 : t1
    float tmin = ray.tmin, tmax = ray.tmax;
    for (int a = 0; a < 3; ++a) {
        tmin = near[a] > tmin ? near[a] : tmin;
        tmax = far[a] < tmax ? far[a] : tmax;
    }
    if (!(tmin <= tmax)) return false;
#if !defined(KDRT_WIDE_AVX2)
    for (int a = 0; a < 3; ++a) {
        r.r8.org[a] = wide::F8{} + o[a];
        r.r8.inv[a] = wide::F8{} + inv[a];
        r.r8.eps[a] = wide::F8{} + eps[a];
    }
#endif
    const F4 zero{};
    r.r8.xyz_org = __builtin_shufflevector(o, zero, 0, 1, 2, 4, 0, 1, 2, 4);
    r.r8.xyz_inv = __builtin_shufflevector(inv, zero, 0, 1, 2, 4, 0, 1, 2, 4);
    r.r8.xyz_eps = __builtin_shufflevector(eps, zero, 0, 1, 2, 4, 0, 1, 2, 4);
    r.ray_tmin = ray.tmin;
    r.ray_tmax = ray.tmax;
    // The root: a wide node, or (a tree of one leaf) that leaf.
    cell = {WideNode::make_slot(WideNode::kSlotNode, 0), tmin, tmax, 0};
    if (tree.wide_nodes.empty()) {
        const KdNode root = tree.nodes[0];
        if (root.prim_count() == 0) return false;
        cell.slot = WideNode::make_slot(WideNode::kSlotLeaf, root.first_ref());
    }
    return true;
}

/// Visits the walk's current cell and moves to the next one. True when the walk has ended: no cell
/// is left that starts no later than the closest hit, or (AnyHit) a hit ended the ray. With
/// AnyHit, `found` then says whether the ray is occluded; otherwise whether `best` holds a hit.
/// Counter: NoCount, or Count (the work counters of kdrt-bench trace --stats).
template <bool AnyHit, class Counter>
[[gnu::always_inline]] static inline bool wide_step(const WideArrays& tree, const WideRay& r,
                                                    wide::Stack& stack, int& stack_size,
                                                    wide::Cell& cell, Best& best, bool& found,
                                                    Counter counter) noexcept {
    counter.steps(cell.steps);
    const uint32_t index = WideNode::slot_index(cell.slot);
    if (WideNode::slot_tag(cell.slot) == WideNode::kSlotNode) {
        counter.wide();
        // Straight onto the stack, farthest first, so the nearest comes off first; the nearest is
        // visited next, without a check (the binary kernel descends to it).
        const int n = wide::decode<Counter::kCounts, Counter::kCounts>(
            tree.wides[index], r.r8, cell.tmin, cell.tmax, stack, stack_size);
        if constexpr (Counter::kCounts) {
            if (n > 0) {
                stack_size += n - 1;
                cell = stack.at(stack_size, Counter::kCounts);
                return false;
            }
        } else {
            // Without a branch on n (whether a ray's interval meets any child is a coin toss
            // for the branch predictor): the nearest child comes off the stack as the others
            // will, skipped when it starts beyond the closest hit. The counting kernels above
            // descend to it unchecked, as the binary kernel does, so they count its steps.
            stack_size += n;
        }
    } else if (!Counter::kCounts || WideNode::slot_tag(cell.slot) == WideNode::kSlotLeaf) {
        // The leaf's run of references, from its slot's first one to the one marked last (only
        // the counting kernels visit empty leaves).
        const uint32_t* ref = tree.refs + index;
        const TriVerts* tris = tree.tris;
        if constexpr (Counter::kCounts) {
            uint32_t n = 1;  // counted before the tests, as the binary kernel counts a leaf
            for (const uint32_t* r = ref; !(*r & KdTree::kLastRef); ++r) ++n;
            counter.leaf(n);
        }
        // A block of references at a time, tested in one pass: eight (wide::intersect8) where
        // the walk has 8-lane permutes, else four (wide::intersect4).
#if defined(KDRT_WIDE_AVX2)
        constexpr int kBlock = 8;
        using UB = uint32_t __attribute__((vector_size(32)));
        using IB = wide::I8;
        const IB lane_id = {0, 1, 2, 3, 4, 5, 6, 7};
        wide::Hits8 h;
#else
        constexpr int kBlock = 4;
        using UB = uint32_t __attribute__((vector_size(16)));
        using IB = wide::I4;
        const IB lane_id = {0, 1, 2, 3};
        wide::Hits4 h;
#endif
        for (bool last = false; !last;) {
            // The block's triangles (indices into tris), a lane each.
            UB block;
            int n = 0;
            if (tree.refs_end - ref >= kBlock) {
                // A block's words in one load: the run ends at the first marked one (or goes on).
                UB words;
                __builtin_memcpy(&words, ref, sizeof words);
                static_assert(KdTree::kLastRef == 0x80000000u);
                const uint32_t marked = wide::lane_bits(reinterpret_cast<IB>(words));
                n = __builtin_ctz(marked | (1u << (kBlock - 1))) + 1;
                last = marked != 0;
                const UB refs = words & ~KdTree::kLastRef;
                const IB in_run = lane_id < n;
                // A short run repeats its first triangle in the spare lanes.
                block = in_run ? refs : UB{} + refs[0];
            } else {
                uint32_t slot[kBlock];
                do {
                    const uint32_t word = ref[n];
                    slot[n++] = word & ~KdTree::kLastRef;
                    last = (word & KdTree::kLastRef) != 0;
                } while (!last && n < kBlock);
                for (int i = n; i < kBlock; ++i) slot[i] = slot[0];
                __builtin_memcpy(&block, slot, sizeof block);
            }
            ref += n;
#if defined(KDRT_WIDE_AVX2)
            uint32_t hits = wide::intersect8(r.p, tris, block, r.ray_tmin, h);
#else
            const TriVerts* const by_ref[kBlock] = {&tris[block[0]], &tris[block[1]],
                                                    &tris[block[2]], &tris[block[3]]};
            uint32_t hits = wide::intersect4(r.p, by_ref, r.ray_tmin, h);
#endif
            if constexpr (AnyHit) {
                if (hits & wide::lane_bits(h.t <= r.ray_tmax)) {
                    found = true;
                    return true;
                }
            } else if (hits != 0) {
                // The lanes' values through memory only on a pass with a hit (most have none).
                alignas(32) float ht[kBlock], hv[kBlock], hw[kBlock], hdet[kBlock];
                alignas(32) uint32_t hblock[kBlock];
                __builtin_memcpy(ht, &h.t, sizeof ht);
                __builtin_memcpy(hv, &h.v, sizeof hv);
                __builtin_memcpy(hw, &h.w, sizeof hw);
                __builtin_memcpy(hdet, &h.det, sizeof hdet);
                __builtin_memcpy(hblock, &block, sizeof hblock);
                for (; hits; hits &= hits - 1) {
                    const int l = __builtin_ctz(hits);
                    const float t = ht[l];
                    // The tie rule and the answer use mesh ids.
                    const uint32_t prim = tree.ids[hblock[l]];
                    if (t < best.t || (t == best.t && prim < best.prim)) {
                        best = {t, prim, hv[l] / hdet[l], hw[l] / hdet[l]};
                        found = true;
                    }
                }
            }
        }
    } else {
        counter.leaf(0);  // an empty leaf
    }
    // The next cell that starts no later than the closest hit (a hit exactly at a cell's entry may
    // still have a lower-id tie inside it). Cells come off the stack front to back, but their
    // intervals are widened by eps, so a later cell (the far side of a plane higher up) may start
    // before an earlier one (a deep near-side cell): the rest of the stack is skipped through,
    // not cut off at the first cell beyond the hit.
    // (In locals: the walk's fields would be stored and reloaded at every cell skipped.)
    int top = stack_size;
    const float best_t = best.t;
    do {
        if (top == 0) {
            stack_size = 0;
            return true;
        }
        --top;
    } while (!AnyHit && stack.tmin[top] > best_t);
    stack_size = top;
    cell = stack.at(top, Counter::kCounts);
    return false;
}

/// Starts the load of the line a cell's visit reads first (its wide node, or its leaf's first
/// references) without waiting for it. A batch walking rays in turn calls it for the cell a walk
/// moves to, so the line is on its way while the other walks take their steps.
[[gnu::always_inline]] static inline void prefetch_cell(const WideArrays& tree,
                                                        uint32_t slot) noexcept {
    // Without a branch: whether the next cell is a node or a leaf is a coin toss for the branch
    // predictor (the turn that visits the cell branches on it anyway), and the address is two
    // selects and a shift.
    const size_t index = WideNode::slot_index(slot);
    const bool node = WideNode::slot_tag(slot) == WideNode::kSlotNode;
    static_assert(sizeof(WideNode) == 64 && sizeof(*tree.refs) == 4);
    const char* base =
        node ? reinterpret_cast<const char*>(tree.wides) : reinterpret_cast<const char*>(tree.refs);
    const int shift = node ? 6 : 2;
    __builtin_prefetch(base + (index << shift));
}

/// Starts the loads of the lines of a leaf cell's first block of triangles (its references must
/// be at hand: prefetch_cell asked for them a turn earlier).
[[gnu::always_inline]] static inline void prefetch_leaf_triangles(const WideArrays& tree,
                                                                  uint32_t slot) noexcept {
    const uint32_t* ref = tree.refs + WideNode::slot_index(slot);
#if defined(KDRT_WIDE_AVX2)
    constexpr int kFirst = 8;
#else
    constexpr int kFirst = 4;
#endif
    if (tree.refs_end - ref < kFirst) return;  // the array's last few: no prefetch
    // The first block's references (eight where the walk tests eight triangles at a time)
    // whether the run ends before them or not (a shorter run's neighbours are its leaf's
    // neighbours in leaf order, often on the same lines).
    // The triangles' offsets in floats (9 an index) in a vector, as intersect8 reads them: each
    // address is then one addressing mode.
    using UF = uint32_t __attribute__((vector_size(4 * kFirst)));
    UF index;
    __builtin_memcpy(&index, ref, sizeof index);
    index &= ~KdTree::kLastRef;
    const UF floats = (index << 3) + index;
    const char* base = reinterpret_cast<const char*>(tree.tris);
#pragma GCC unroll 8
    for (int i = 0; i < kFirst; ++i) {
        const char* t = base + static_cast<size_t>(floats[i]) * sizeof(float);
        __builtin_prefetch(t);
        __builtin_prefetch(t + sizeof(TriVerts) - 1);
    }
}

/// The single-ray kernel: with AnyHit it returns at the first hit in [ray tmin, ray tmax];
/// otherwise it keeps the lexicographically smallest (t, prim) so ties do not depend on the
/// traversal order. Counter: NoCount, or Count (the work counters of kdrt-bench trace --stats).
template <bool AnyHit, class Counter>
static inline bool traverse_wide(const KdTree& tree, const Ray& ray, Best& best,
                                 Counter counter) noexcept {
    WideRay r;          // NOLINT(cppcoreguidelines-pro-type-member-init): wide_start sets it
    wide::Cell cell;    // NOLINT(cppcoreguidelines-pro-type-member-init): wide_start sets it
    wide::Stack stack;  // NOLINT(cppcoreguidelines-pro-type-member-init): written before read
    const WideArrays arrays(tree);
    if (!wide_start(tree, arrays, ray, r, cell)) return false;
    int stack_size = 0;
    bool found = false;
    while (!wide_step<AnyHit>(arrays, r, stack, stack_size, cell, best, found, counter)) {
    }
    return found;
}

static inline Hit to_hit(bool found, const Best& best) noexcept {
    return found ? Hit{best.t, best.prim, best.u, best.v} : Hit{};
}

/// The single-ray queries (PacketKernels::single_*): intersect / occluded of trace.h, and their
/// counting copies.
static inline Hit wide_intersect(const KdTree& tree, const Ray& ray) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    const bool found = traverse_wide<false>(tree, ray, best, NoCount{});
    return to_hit(found, best);
}
static inline bool wide_occluded(const KdTree& tree, const Ray& ray) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    return traverse_wide<true>(tree, ray, best, NoCount{});
}
static inline Hit wide_intersect_counted(const KdTree& tree, const Ray& ray,
                                         TraceCounters& counters) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    const bool found = traverse_wide<false>(tree, ray, best, Count{counters});
    return to_hit(found, best);
}
static inline bool wide_occluded_counted(const KdTree& tree, const Ray& ray,
                                         TraceCounters& counters) noexcept {
    Best best{ray.tmax, kNoHit, 0.0f, 0.0f};
    return traverse_wide<true>(tree, ray, best, Count{counters});
}

}  // namespace
}  // namespace kdrt::detail
