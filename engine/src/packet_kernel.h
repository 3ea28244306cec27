#pragma once
// Internal: packet traversal of the kD-tree (Stoll 2005: "if any ray wants to go left, go left
// with mask"), one template over the SIMD width W. Included only by the per-ISA translation units
// after their `#pragma GCC target`; everything is in an anonymous namespace (see simd.h).
//
// Per lane the kernel makes exactly the scalar kernel's decisions (trace.cpp): the same widened
// cell intervals, the same culling of stack entries against the lane's closest hit, the same
// watertight triangle test and tie rule. A lane is active in a cell when its interval there is
// not empty; the packet descends into a child when any active lane needs it. So every lane tests
// exactly the triangles its single ray would, and the answers are bit-identical.

#include "batch_schedule.h"
#include "packet.h"
#include "ray_prep.h"
#include "simd.h"
#include "wide_kernel.h"

#include <array>
#include <bit>

namespace kdrt::detail {
namespace {

template <int W>
using VF = simd::Float<W>;
template <int W>
using VM = simd::Mask<W>;
template <int W>
using VU = simd::UInt<W>;

/// A packet's rays in SoA form with their per-lane set-up.
template <int W>
struct alignas(64) Packet {
    VF<W> org[3];
    VF<W> inv[3];
    VF<W> eps[3];
    VF<W> org_k[3];  // the origin permuted into the lane's (kx, ky, kz) frame
    VF<W> sx, sy, sz;
    VM<W> kx, ky, kz;
    // Per lane, which float of 16 loaded bytes is the lane's kx, ky, kz coordinate (sel[0..2]),
    // and the same one float further on (sel[3..5]), in permute4's form for the ISA.
    VM<W> sel[6];
    VF<W> ray_tmin, ray_tmax;
    VF<W> tmin, tmax;  // the root interval: the ray clipped to the scene box (empty for dead lanes)
    uint32_t near_is_high[3];
    int uniform_k;  // -1, or the kz shared by every lane (then kx, ky are shared too)
};

template <int W>
struct alignas(64) StackEntry {
    VF<W> tmin, tmax;
    uint32_t node;
};

/// Best hit per lane.
template <int W>
struct alignas(64) PacketHits {
    VF<W> t, u, v;
    VU<W> prim;
};

/// Lane-wise choice of one of three per-axis values: k == 0 ? x : k == 1 ? y : z.
template <int W>
inline VF<W> pick(VM<W> k, VF<W> x, VF<W> y, VF<W> z) {
    return k == 0 ? x : (k == 1 ? y : z);
}

/// A lane selector for permute4: float `k` (0..3) of the 16 bytes.
template <int W>
inline VM<W> selector(VM<W> k) {
    if constexpr (W == 4) {
        return k * 0x04040404 + 0x03020100;  // pshufb: the four bytes of float k
    } else {
        return k;
    }
}

/// Lane-wise v[sel]: per lane, one of the four floats at v (16 readable bytes), chosen by the
/// lane's selector, in one permute (pshufb on SSE4, vpermps on AVX2 and AVX-512).
template <int W>
inline VF<W> permute4(const float* v, VM<W> sel) {
    if constexpr (W == 4) {
        const __m128i bytes = _mm_loadu_si128(reinterpret_cast<const __m128i*>(v));
        return reinterpret_cast<VF<W>>(_mm_shuffle_epi8(bytes, reinterpret_cast<__m128i>(sel)));
    } else if constexpr (W == 8) {
        const __m256 four = _mm256_broadcast_ps(reinterpret_cast<const __m128*>(v));
        return reinterpret_cast<VF<W>>(
            _mm256_permutevar8x32_ps(four, reinterpret_cast<__m256i>(sel)));
    } else {
        // (The maskz forms with every lane set: the unmasked intrinsics trip GCC 12's
        // uninitialized warnings on their undefined pass-through operand.)
        const __m512 four = _mm512_maskz_broadcast_f32x4(0xFFFF, _mm_loadu_ps(v));
        return reinterpret_cast<VF<W>>(
            _mm512_maskz_permutexvar_ps(0xFFFF, reinterpret_cast<__m512i>(sel), four));
    }
}

template <int W>
inline VF<W> abs(VF<W> x) {
    VU<W> bits;
    __builtin_memcpy(&bits, &x, sizeof bits);
    bits &= 0x7FFFFFFFu;
    __builtin_memcpy(&x, &bits, sizeof x);
    return x;
}

/// The rays rays[index[0..W)] as eight SoA vectors, one per field in Ray's order (ox, oy, oz,
/// tmin, dx, dy, dz, tmax); lanes at or past `count` repeat ray index[0]. A 4x4 transpose of
/// each half-ray (16 bytes) per group of four lanes: the copy costs about 3 instructions per
/// ray instead of the 8 loads and 8 stores of a lane-by-lane copy.
template <int W>
inline void load_rays_soa(const Ray* rays, const uint16_t* index, int count, VF<W> field[8]) {
    const float* ray[W];
    for (int l = 0; l < W; ++l) ray[l] = &rays[index[l < count ? l : 0]].ox;
    if constexpr (W == 4) {
        for (int half = 0; half < 2; ++half) {
            __m128 r0 = _mm_loadu_ps(ray[0] + 4 * half), r1 = _mm_loadu_ps(ray[1] + 4 * half),
                   r2 = _mm_loadu_ps(ray[2] + 4 * half), r3 = _mm_loadu_ps(ray[3] + 4 * half);
            _MM_TRANSPOSE4_PS(r0, r1, r2, r3);
            field[4 * half + 0] = reinterpret_cast<VF<W>>(r0);
            field[4 * half + 1] = reinterpret_cast<VF<W>>(r1);
            field[4 * half + 2] = reinterpret_cast<VF<W>>(r2);
            field[4 * half + 3] = reinterpret_cast<VF<W>>(r3);
        }
    } else {
        // Groups of eight lanes: lanes g..g+3 in the low 128 bits, g+4..g+7 in the high ones.
        __m256 out[W / 8][8];
        for (int g = 0; g < W / 8; ++g) {
            const float* const* r = &ray[8 * g];
            for (int half = 0; half < 2; ++half) {
                const int o = 4 * half;
                const __m256 a = _mm256_insertf128_ps(
                    _mm256_castps128_ps256(_mm_loadu_ps(r[0] + o)), _mm_loadu_ps(r[4] + o), 1);
                const __m256 b = _mm256_insertf128_ps(
                    _mm256_castps128_ps256(_mm_loadu_ps(r[1] + o)), _mm_loadu_ps(r[5] + o), 1);
                const __m256 c = _mm256_insertf128_ps(
                    _mm256_castps128_ps256(_mm_loadu_ps(r[2] + o)), _mm_loadu_ps(r[6] + o), 1);
                const __m256 d = _mm256_insertf128_ps(
                    _mm256_castps128_ps256(_mm_loadu_ps(r[3] + o)), _mm_loadu_ps(r[7] + o), 1);
                const __m256 ab_lo = _mm256_unpacklo_ps(a, b), ab_hi = _mm256_unpackhi_ps(a, b);
                const __m256 cd_lo = _mm256_unpacklo_ps(c, d), cd_hi = _mm256_unpackhi_ps(c, d);
                out[g][o + 0] = _mm256_shuffle_ps(ab_lo, cd_lo, _MM_SHUFFLE(1, 0, 1, 0));
                out[g][o + 1] = _mm256_shuffle_ps(ab_lo, cd_lo, _MM_SHUFFLE(3, 2, 3, 2));
                out[g][o + 2] = _mm256_shuffle_ps(ab_hi, cd_hi, _MM_SHUFFLE(1, 0, 1, 0));
                out[g][o + 3] = _mm256_shuffle_ps(ab_hi, cd_hi, _MM_SHUFFLE(3, 2, 3, 2));
            }
        }
        for (int f = 0; f < 8; ++f) {
            if constexpr (W == 8) {
                field[f] = reinterpret_cast<VF<W>>(out[0][f]);
            } else {
                // (__builtin_shufflevector: the insert intrinsics trip GCC 12's uninitialized
                // warnings on their undefined upper halves.)
                field[f] = reinterpret_cast<VF<W>>(__builtin_shufflevector(
                    out[0][f], out[1][f], 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
            }
        }
    }
}

/// One lane's Hit record (16 bytes) to hits[base + index[l]], if the lane holds a ray. (Helpers
/// here are functions, not lambdas: a lambda would not inherit the ISA target.)
inline void put_hit(Hit* hits, size_t base, const uint16_t* index, int count, int l,
                    __m128 record) {
    if (l < count) _mm_storeu_ps(reinterpret_cast<float*>(&hits[base + index[l]]), record);
}

/// Lanes 8g..8g+7 of a 16-lane vector (a template, so only the AVX-512 unit instantiates it).
template <int W>
inline __m256 half8(VF<W> x, int g) {
    return g == 0 ? __builtin_shufflevector(x, x, 0, 1, 2, 3, 4, 5, 6, 7)
                  : __builtin_shufflevector(x, x, 8, 9, 10, 11, 12, 13, 14, 15);
}

/// Writes lanes 0..count) of a packet's answers, as Hit records, to hits[base + index[l]]: a miss
/// (prim kNoHit) as Hit{} (t = inf, u = v = 0). The four fields are transposed into records four
/// lanes at a time.
template <int W>
inline void store_hits(const PacketHits<W>& best, const uint16_t* index, int count, size_t base,
                       Hit* hits) {
    const VM<W> miss = best.prim == simd::broadcast_u<W>(kNoHit);
    const VF<W> t = simd::select<W>(miss, simd::broadcast<W>(__builtin_inff()), best.t);
    const VF<W> u = simd::select<W>(miss, simd::broadcast<W>(0.0f), best.u);
    const VF<W> v = simd::select<W>(miss, simd::broadcast<W>(0.0f), best.v);
    VF<W> prim;
    __builtin_memcpy(&prim, &best.prim, sizeof prim);
    if constexpr (W == 4) {
        __m128 r0 = reinterpret_cast<__m128>(t), r1 = reinterpret_cast<__m128>(prim),
               r2 = reinterpret_cast<__m128>(u), r3 = reinterpret_cast<__m128>(v);
        _MM_TRANSPOSE4_PS(r0, r1, r2, r3);
        put_hit(hits, base, index, count, 0, r0);
        put_hit(hits, base, index, count, 1, r1);
        put_hit(hits, base, index, count, 2, r2);
        put_hit(hits, base, index, count, 3, r3);
    } else {
        for (int g = 0; g < W / 8; ++g) {
            __m256 tg, pg, ug, vg;
            if constexpr (W == 8) {
                tg = reinterpret_cast<__m256>(t);
                pg = reinterpret_cast<__m256>(prim);
                ug = reinterpret_cast<__m256>(u);
                vg = reinterpret_cast<__m256>(v);
            } else {
                tg = half8<W>(t, g);
                pg = half8<W>(prim, g);
                ug = half8<W>(u, g);
                vg = half8<W>(v, g);
            }
            const __m256 tp_lo = _mm256_unpacklo_ps(tg, pg), tp_hi = _mm256_unpackhi_ps(tg, pg);
            const __m256 uv_lo = _mm256_unpacklo_ps(ug, vg), uv_hi = _mm256_unpackhi_ps(ug, vg);
            const __m256 rec[4] = {_mm256_shuffle_ps(tp_lo, uv_lo, _MM_SHUFFLE(1, 0, 1, 0)),
                                   _mm256_shuffle_ps(tp_lo, uv_lo, _MM_SHUFFLE(3, 2, 3, 2)),
                                   _mm256_shuffle_ps(tp_hi, uv_hi, _MM_SHUFFLE(1, 0, 1, 0)),
                                   _mm256_shuffle_ps(tp_hi, uv_hi, _MM_SHUFFLE(3, 2, 3, 2))};
            for (int k = 0; k < 4; ++k) {
                put_hit(hits, base, index, count, 8 * g + k, _mm256_castps256_ps128(rec[k]));
                put_hit(hits, base, index, count, 8 * g + 4 + k, _mm256_extractf128_ps(rec[k], 1));
            }
        }
    }
}

/// Loads `count` (1..W) valid rays into a packet, computing lane by lane what prepare_ray,
/// clip_to_box and traversal_eps compute for a single ray, with the same operations in the same
/// order. Lanes past `count` are dead (empty interval).
template <int W>
inline void setup_packet(const KdTree& tree, const Ray* rays, const uint16_t* index, int count,
                         Packet<W>& pk) {
    VF<W> field[8];
    load_rays_soa<W>(rays, index, count, field);
    const VF<W> o[3] = {field[0], field[1], field[2]};
    const VF<W> d[3] = {field[4], field[5], field[6]};
    const VF<W> ray_tmin = field[3], ray_tmax = field[7];
    VF<W> inv[3];
    for (int a = 0; a < 3; ++a) inv[a] = 1.0f / d[a];
    // prepare_ray: kz where |d| is largest (first on ties), kx and ky after it, swapped when
    // d[kz] < 0; the shear constants.
    const VF<W> ad0 = abs<W>(d[0]), ad1 = abs<W>(d[1]), ad2 = abs<W>(d[2]);
    VM<W> kz = simd::select<W>(ad1 > ad0, simd::broadcast_i<W>(1), simd::broadcast_i<W>(0));
    kz = simd::select<W>(ad2 > (kz == 0 ? ad0 : ad1), simd::broadcast_i<W>(2), kz);
    VM<W> kx = simd::select<W>(kz == 2, simd::broadcast_i<W>(0), kz + 1);
    VM<W> ky = simd::select<W>(kx == 2, simd::broadcast_i<W>(0), kx + 1);
    const VF<W> dkz = pick<W>(kz, d[0], d[1], d[2]);
    const VM<W> swap = dkz < 0.0f;
    const VM<W> kx_swapped = simd::select<W>(swap, ky, kx);
    ky = simd::select<W>(swap, kx, ky);
    kx = kx_swapped;
    pk.sx = pick<W>(kx, d[0], d[1], d[2]) / dkz;
    pk.sy = pick<W>(ky, d[0], d[1], d[2]) / dkz;
    pk.sz = 1.0f / dkz;
    pk.kx = kx;
    pk.ky = ky;
    pk.kz = kz;
    pk.sel[0] = selector<W>(kx);
    pk.sel[1] = selector<W>(ky);
    pk.sel[2] = selector<W>(kz);
    pk.sel[3] = selector<W>(kx + 1);
    pk.sel[4] = selector<W>(ky + 1);
    pk.sel[5] = selector<W>(kz + 1);
    pk.org_k[0] = pick<W>(kx, o[0], o[1], o[2]);
    pk.org_k[1] = pick<W>(ky, o[0], o[1], o[2]);
    pk.org_k[2] = pick<W>(kz, o[0], o[1], o[2]);
    // traversal_eps (interval_margin first: the clip is widened by it)
    const VF<W> inf = simd::broadcast<W>(__builtin_inff());
    VF<W> m = simd::broadcast<W>(bounds_magnitude(tree.bounds));
    for (int a = 0; a < 3; ++a) {
        const VF<W> oa = abs<W>(o[a]);
        m = simd::select<W>(oa > m, oa, m);
    }
    const VF<W> delta = m * 0x1p-20f;
    for (int a = 0; a < 3; ++a) {
        const VF<W> ai = abs<W>(inv[a]);
        pk.eps[a] = simd::select<W>(ai == inf, simd::broadcast<W>(0.0f), delta * ai);
        pk.org[a] = o[a];
        pk.inv[a] = inv[a];
    }
    // clip_to_box
    VF<W> tmin = ray_tmin, tmax = ray_tmax;
    VM<W> miss = simd::broadcast_i<W>(0);
    for (int a = 0; a < 3; ++a) {
        const VM<W> parallel = abs<W>(inv[a]) == inf;
        miss |= parallel & ((o[a] < tree.bounds.lo[a]) | (o[a] > tree.bounds.hi[a]));
        const VF<W> t0 = (tree.bounds.lo[a] - o[a]) * inv[a],
                    t1 = (tree.bounds.hi[a] - o[a]) * inv[a];
        const VM<W> order = t0 > t1;
        const VF<W> near = simd::select<W>(order, t1, t0) - pk.eps[a],
                    far = simd::select<W>(order, t0, t1) + pk.eps[a];
        tmin = simd::select<W>(parallel, tmin, simd::select<W>(near > tmin, near, tmin));
        tmax = simd::select<W>(parallel, tmax, simd::select<W>(far < tmax, far, tmax));
    }
    alignas(64) int32_t lane[W];
    for (int l = 0; l < W; ++l) lane[l] = l;
    VM<W> lane_v;
    __builtin_memcpy(&lane_v, lane, sizeof lane_v);
    const VM<W> alive = (lane_v < count) & ~miss & (tmin <= tmax);
    pk.tmin = simd::select<W>(alive, tmin, inf);
    pk.tmax = simd::select<W>(alive, tmax, -inf);
    pk.ray_tmin = ray_tmin;
    pk.ray_tmax = ray_tmax;
    for (int a = 0; a < 3; ++a) pk.near_is_high[a] = __builtin_signbit(d[a][0]) ? 1u : 0u;
    const int kz0 = pk.kz[0];
    pk.uniform_k = simd::none<W>(kz != kz0) && simd::none<W>(kx != pk.kx[0]) ? kz0 : -1;
}

/// The watertight test of one triangle against the lanes in `active`; returns the lanes hit with
/// tmin <= t (per lane t, u, v written). Same arithmetic as intersect_triangle, lane by lane.
/// Uniform: every lane has the frame (kx, ky, kz) (pk.uniform_k >= 0; the caller passes it, read
/// once per packet), so each coordinate is one broadcast; else one permute per coordinate.
template <int W, bool Uniform>
[[gnu::always_inline]] inline VM<W> intersect_triangle_in_frame(const Packet<W>& pk, int kx, int ky,
                                                                int kz, const TriVerts& tri,
                                                                VM<W> active, VF<W>& t_out,
                                                                VF<W>& u_out, VF<W>& v_out) {
    // The vertices relative to the origin in each lane's (kx, ky, kz) frame: tri.v[k] - org[k].
    VF<W> a_x, a_y, a_z, b_x, b_y, b_z, c_x, c_y, c_z;
    if constexpr (Uniform) {
        a_x = tri.v0[kx] - pk.org_k[0], a_y = tri.v0[ky] - pk.org_k[1],
        a_z = tri.v0[kz] - pk.org_k[2];
        b_x = tri.v1[kx] - pk.org_k[0], b_y = tri.v1[ky] - pk.org_k[1],
        b_z = tri.v1[kz] - pk.org_k[2];
        c_x = tri.v2[kx] - pk.org_k[0], c_y = tri.v2[ky] - pk.org_k[1],
        c_z = tri.v2[kz] - pk.org_k[2];
    } else {
        // One permute per coordinate. The 16 bytes read stay inside the 36-byte triangle: v0 and
        // v1 from their first float, v2 from v1[2] (so its selectors are one float further on).
        a_x = permute4<W>(tri.v0, pk.sel[0]) - pk.org_k[0];
        a_y = permute4<W>(tri.v0, pk.sel[1]) - pk.org_k[1];
        a_z = permute4<W>(tri.v0, pk.sel[2]) - pk.org_k[2];
        b_x = permute4<W>(tri.v1, pk.sel[0]) - pk.org_k[0];
        b_y = permute4<W>(tri.v1, pk.sel[1]) - pk.org_k[1];
        b_z = permute4<W>(tri.v1, pk.sel[2]) - pk.org_k[2];
        c_x = permute4<W>(&tri.v1[2], pk.sel[3]) - pk.org_k[0];
        c_y = permute4<W>(&tri.v1[2], pk.sel[4]) - pk.org_k[1];
        c_z = permute4<W>(&tri.v1[2], pk.sel[5]) - pk.org_k[2];
    }
    const VF<W> ax = a_x - pk.sx * a_z, ay = a_y - pk.sy * a_z;
    const VF<W> bx = b_x - pk.sx * b_z, by = b_y - pk.sy * b_z;
    const VF<W> cx = c_x - pk.sx * c_z, cy = c_y - pk.sy * c_z;
    VF<W> u = cx * by - cy * bx;
    VF<W> v = ax * cy - ay * cx;
    VF<W> w = bx * ay - by * ax;
    // Lanes outside `active` may take the retry too: their answers are masked off below.
    const VM<W> zero_edge = (u == 0.0f) | (v == 0.0f) | (w == 0.0f);
    if (simd::any<W>(zero_edge)) [[unlikely]] {
        // The scalar kernel's double-precision retry, for the lanes that need it.
        alignas(64) float fu[W], fv[W], fw[W], fax[W], fay[W], fbx[W], fby[W], fcx[W], fcy[W];
        simd::store<W>(fu, u);
        simd::store<W>(fv, v);
        simd::store<W>(fw, w);
        simd::store<W>(fax, ax);
        simd::store<W>(fay, ay);
        simd::store<W>(fbx, bx);
        simd::store<W>(fby, by);
        simd::store<W>(fcx, cx);
        simd::store<W>(fcy, cy);
        for (uint32_t m = simd::bits<W>(zero_edge); m; m &= m - 1) {
            const int l = __builtin_ctz(m);
            exact_edges(fax[l], fay[l], fbx[l], fby[l], fcx[l], fcy[l], fu[l], fv[l], fw[l]);
        }
        u = simd::load<W>(fu);
        v = simd::load<W>(fv);
        w = simd::load<W>(fw);
    }
    // The scalar test's "not outside (an edge function below 0 and one above) and det != 0", in
    // fewer operations: with lo and hi the least and greatest of u, v, w, a lane passes when
    // exactly one of lo < 0 and hi > 0 holds. Both: outside. Neither: u = v = w = 0 (det = 0).
    // Only lo < 0: all <= 0, not all 0, so det < 0 (a sum of non-positive floats is 0 only when
    // each is); likewise only hi > 0. A NaN among them makes det and t NaN, and the t >= tmin
    // test below rejects the lane whatever min and max make of the NaN, as the scalar test does.
    const VF<W> det = u + v + w;
    const VF<W> lo = simd::min<W>(simd::min<W>(u, v), w);
    const VF<W> hi = simd::max<W>(simd::max<W>(u, v), w);
    VM<W> hit = active & ((lo < 0.0f) ^ (hi > 0.0f));
    if (simd::none<W>(hit)) return hit;
    const VF<W> az = pk.sz * a_z, bz = pk.sz * b_z, cz = pk.sz * c_z;
    const VF<W> t_scaled = u * az + v * bz + w * cz;
    const VF<W> t = t_scaled / det;
    hit &= t >= pk.ray_tmin;
    t_out = t;
    u_out = v / det;
    v_out = w / det;
    return hit;
}

/// intersect_triangle_in_frame with the packet's frame read per call (for callers outside the
/// packet walk's leaf loop).
template <int W>
inline VM<W> intersect_triangle_packet(const Packet<W>& pk, const TriVerts& tri, VM<W> active,
                                       VF<W>& t_out, VF<W>& u_out, VF<W>& v_out) {
    if (pk.uniform_k >= 0)
        return intersect_triangle_in_frame<W, true>(pk, pk.kx[0], pk.ky[0], pk.uniform_k, tri,
                                                    active, t_out, u_out, v_out);
    return intersect_triangle_in_frame<W, false>(pk, 0, 0, 0, tri, active, t_out, u_out, v_out);
}

/// Live lanes of a mask.
template <int W>
inline uint64_t live_lanes(VM<W> m) {
    return static_cast<uint64_t>(__builtin_popcount(simd::bits<W>(m)));
}

/// Counts a packet's visit of a node: its live lanes, into `per_ray` (steps or leaves) and the
/// lane-use totals.
template <int W>
inline void count_visit(VM<W> active, uint64_t& per_ray, TraceCounters& counters) {
    const uint64_t live = live_lanes<W>(active);
    per_ray += live;
    counters.packet_lanes += live;
    ++counters.packet_visits;
}

/// The leaf of `n` references at `ref` for the lanes in `live`, lane by lane, four triangles a
/// pass (wide::intersect4): closest hit into `best` with the packet's tie rule; any hit returns
/// the lanes occluded (and puts an occluder's tree slot in best.prim of each, for the
/// OccluderCache). Each lane's prepared ray is the packet's set-up of that lane (the same
/// values prepare_ray gives), so its answers are the packet test's.
template <int W, bool AnyHit>
inline VM<W> leaf_by_lanes(const Packet<W>& pk, uint32_t live, const uint32_t* ref, uint32_t n,
                           const TriVerts* tris, const uint32_t* ids, PacketHits<W>& best) {
    VM<W> occluded = simd::broadcast_i<W>(0);
    for (; live; live &= live - 1) {
        const int l = __builtin_ctz(live);
        PreparedRay p;
        for (int a = 0; a < 3; ++a) p.org[a] = pk.org[a][l];  // intersect4 reads no inv_dir
        p.kx = pk.kx[l];
        p.ky = pk.ky[l];
        p.kz = pk.kz[l];
        p.sx = pk.sx[l];
        p.sy = pk.sy[l];
        p.sz = pk.sz[l];
        const float ray_tmin = pk.ray_tmin[l], ray_tmax = pk.ray_tmax[l];
        for (uint32_t r = 0; r < n; r += 4) {
            uint32_t slot[4];
            if (n - r >= 4) {
                for (uint32_t i = 0; i < 4; ++i) slot[i] = ref[r + i] & ~KdTree::kLastRef;
            } else {  // a short block repeats its first triangle in the spare lanes
                const uint32_t k = n - r;
                for (uint32_t i = 0; i < 4; ++i)
                    slot[i] = ref[r + (i < k ? i : 0)] & ~KdTree::kLastRef;
            }
            const TriVerts* const block[4] = {&tris[slot[0]], &tris[slot[1]], &tris[slot[2]],
                                              &tris[slot[3]]};
            wide::Hits4 h;
            uint32_t hits = wide::intersect4(p, block, ray_tmin, h);
            if constexpr (AnyHit) {
                if (const uint32_t in = hits & wide::bits4(h.t <= ray_tmax)) {
                    occluded[l] = -1;
                    best.prim[l] = slot[__builtin_ctz(in)];  // the occluder (OccluderCache)
                    break;
                }
            } else {
                for (; hits; hits &= hits - 1) {
                    const int j = __builtin_ctz(hits);
                    const float t = h.t[j];
                    const uint32_t prim = ids[slot[j]];
                    if (t < best.t[l] || (t == best.t[l] && prim < best.prim[l])) {
                        best.t[l] = t;
                        best.u[l] = h.v[j] / h.det[j];
                        best.v[l] = h.w[j] / h.det[j];
                        best.prim[l] = prim;
                    }
                }
            }
        }
    }
    return occluded;
}

/// The triangles a packet has tested, and for which lanes: a direct-mapped record of the last
/// triangle (tree slot) seen at each of kEntries positions (slot % kEntries), with the union of
/// the lanes that tested it since it took the position. A kD-tree lists a triangle in every leaf
/// it overlaps, so a packet crossing several of them meets it again (on the stadium's primary
/// rays a quarter of the packet tests are such repeats). A closest-hit test of a triangle whose
/// active lanes have all tested it before in this packet is skipped; proof that this changes no
/// answer at leaf_packet. Slots are below 2^31 (kLastRef is their top bit), so the empty mark
/// ~0u matches none.
struct PacketMailbox {
    static constexpr uint32_t kEntries = 32;
    uint64_t entry[kEntries];  // the slot in the low word, its lanes in the high word
    void clear() {
        for (uint64_t& e : entry) e = ~0u;
    }
    /// Records that the lanes `live_high` (in the high word) test triangle `s`, without looking
    /// (the packet's first leaf: no repeats yet, and each triangle is in a leaf once).
    [[gnu::always_inline]] void record(uint32_t s, uint64_t live_high) {
        entry[s % kEntries] = live_high | s;
    }
    /// Whether every lane of `live` has tested triangle `s` already; if not, records that they
    /// now have (the caller then tests it).
    [[gnu::always_inline]] bool seen(uint32_t s, uint32_t live) {
        uint64_t& e = entry[s % kEntries];
        const uint64_t x = e;
        const uint64_t before = static_cast<uint32_t>(x) == s ? x : s;
        const uint64_t now = before | (static_cast<uint64_t>(live) << 32);
        if (now == before) return true;
        e = now;
        return false;
    }
};

/// Whether a closest-hit packet uses the mailbox: it pays where a good share of the tests it
/// looks up are repeats (bunny primary, AVX2: a look-up and record cost about 10 instructions and
/// save a ~60-instruction test; the stadium skips about a quarter of its tests, the bunny, dragon
/// and diplodocus 6-9%). Measured per thread as the walk goes: always for the first packets,
/// then while the skipped share stays at 1/kMailPaysShare or more, and one packet in 64 anyway
/// to keep measuring. The choice changes no answer, only the work.
constexpr uint64_t kMailWarmUp = 4096, kMailPaysShare = 6;
inline bool mailbox_pays(const TraceCounters& c) {
    return c.mail_looked < kMailWarmUp || c.mail_skipped * kMailPaysShare >= c.mail_looked ||
           (c.packets & 63) == 0;
}

/// What leaf_packet does with the mailbox: nothing (any hit), record the triangles it tests (the
/// packet's first leaf with tests), or skip the repeats and record the rest.
constexpr int kMailNone = 0, kMailRecord = 1, kMailSkip = 2;

/// Tests the leaf's references refs[r, end) against the packet's lanes in `active`, one packet
/// test per triangle in the frame of intersect_triangle_in_frame<W, Uniform>: closest hit into
/// `best` with the packet's tie rule; any hit adds the lanes occluded to `done` (an occluder's
/// tree slot to their best.prim, for the OccluderCache) and stops when every active lane is.
///
/// Closest hit skips a triangle that `mailbox` says every active lane has tested already. That
/// changes no answer: a lane's test of a triangle depends only on the lane's ray and the
/// triangle (not on `active`, the cell or the order of tests), so a repeat gives the lane the
/// same (t, u, v, hit). The update keeps the least (t, prim) in lexicographic order, and a lane's
/// best only ever decreases in that order, so after the first test best <= (t, prim) and the
/// repeat's condition t < best.t || (t == best.t && prim < best.prim) is false (a NaN t fails it
/// both times). Since each mesh triangle has one slot and one id, an equal (t, prim) is the same
/// hit, so the tie rule between equal t is untouched too. Hits beyond the current cell are kept
/// by the first test, as the scalar kernel keeps them, so nothing waits for a later cell.
/// Count: the work counters keep the scalar kernel's tests (a skipped lane still counts in
/// tri_tests, so the per-ray figures compare across kernels); the skipped lanes count apart.
template <int W, bool AnyHit, bool Count, bool Uniform, int Mail>
requires(!AnyHit || Mail == kMailNone) [[gnu::always_inline]] inline void leaf_packet(
    const Packet<W>& pk, int kx, int ky, int kz, const uint32_t* refs, uint32_t r, uint32_t end,
    const TriVerts* tris, const uint32_t* ids, VM<W> active, VM<W>& done, PacketHits<W>& best,
    PacketMailbox& mailbox, TraceCounters& counters) {
    const uint32_t live = simd::bits<W>(active);  // constant for closest hit
    if constexpr (Mail == kMailSkip) counters.mail_looked += end - r;
    for (; r < end; ++r) {
        const uint32_t slot = refs[r] & ~KdTree::kLastRef;
        if constexpr (Count) counters.tri_tests += live_lanes<W>(active);
        if constexpr (Mail == kMailRecord) mailbox.record(slot, uint64_t{live} << 32);
        if constexpr (Mail == kMailSkip) {
            if (mailbox.seen(slot, live)) {
                ++counters.mail_skipped;
                if constexpr (Count) counters.tri_skips += live_lanes<W>(active);
                continue;
            }
        }
        VF<W> t, u, v;
        VM<W> hit =
            intersect_triangle_in_frame<W, Uniform>(pk, kx, ky, kz, tris[slot], active, t, u, v);
        if (simd::none<W>(hit)) continue;
        if constexpr (AnyHit) {
            hit &= t <= pk.ray_tmax;
            best.prim = simd::select<W>(hit, simd::broadcast_u<W>(slot), best.prim);  // occluder
            done |= hit;
            active &= ~hit;
            if (simd::none<W>(active)) break;
        } else {
            const VU<W> prim_v = simd::broadcast_u<W>(ids[slot]);  // mesh ids
            hit &= (t < best.t) | ((t == best.t) & (prim_v < best.prim));
            best.t = simd::select<W>(hit, t, best.t);
            best.u = simd::select<W>(hit, u, best.u);
            best.v = simd::select<W>(hit, v, best.v);
            best.prim = simd::select<W>(hit, prim_v, best.prim);
        }
    }
}

/// leaf_packet in the packet's frame: the uniform one when kz >= 0 (then kx, ky, kz are every
/// lane's), else each lane's own.
template <int W, bool AnyHit, bool Count, int Mail>
[[gnu::always_inline]] inline void leaf_in_frame(const Packet<W>& pk, int kx, int ky, int kz,
                                                 const uint32_t* refs, uint32_t r, uint32_t end,
                                                 const TriVerts* tris, const uint32_t* ids,
                                                 VM<W> active, VM<W>& done, PacketHits<W>& best,
                                                 PacketMailbox& mailbox, TraceCounters& counters) {
    if (kz >= 0)
        leaf_packet<W, AnyHit, Count, true, Mail>(pk, kx, ky, kz, refs, r, end, tris, ids, active,
                                                  done, best, mailbox, counters);
    else
        leaf_packet<W, AnyHit, Count, false, Mail>(pk, 0, 0, 0, refs, r, end, tris, ids, active,
                                                   done, best, mailbox, counters);
}

/// Traverses the tree with one packet. Closest hit: `best` holds per-lane answers (initialised by
/// the caller to t = ray tmax, prim = kNoHit). Any hit: returns the lanes occluded.
/// Mail: use the mailbox (closest hit only; the caller asks mailbox_pays). A template parameter,
/// not a flag, so that the walk without it is the plain walk, instruction for instruction.
template <int W, bool AnyHit, bool Count, bool Mail>
requires(!AnyHit || !Mail) inline VM<W> traverse_packet(const KdTree& tree, const Packet<W>& pk,
                                                        PacketHits<W>& best,
                                                        TraceCounters& counters) {
    const KdNode* nodes = tree.nodes.data();
    const uint32_t* refs = tree.leaf_refs.data();
    const TriVerts* tris = tree.tris.data();
    const uint32_t* ids = tree.tri_ids.data();
    StackEntry<W> stack[kMaxDepth + 1];
    int stack_size = 0;
    VM<W> done = simd::broadcast_i<W>(0);  // any-hit lanes already occluded
    VF<W> tmin = pk.tmin, tmax = pk.tmax;
    uint32_t node_index = 0;
    if (simd::none<W>(tmin <= tmax)) return done;
    const int uniform_kz = pk.uniform_k, uniform_kx = pk.kx[0], uniform_ky = pk.ky[0];
    PacketMailbox mailbox;  // cleared at the first leaf with tests (Mail only)
    bool mailbox_used = false;
    for (;;) {
        KdNode node = nodes[node_index];
        while (!node.is_leaf()) {
            // The split broadcast straight from the node's second word (KdNode: word1 is the
            // split, at byte 4, as the static_assert proves), the axis unsigned (no sign
            // extension for the indexing).
            static_assert(std::bit_cast<std::array<uint32_t, 2>>(KdNode::from_words(1, 2))[1] == 2);
            const auto axis = static_cast<uint32_t>(node.axis());
            float split;
            __builtin_memcpy(&split, reinterpret_cast<const char*>(&nodes[node_index]) + 4,
                             sizeof split);
            const VF<W> t_split = (split - pk.org[axis]) * pk.inv[axis];
            const VF<W> near_max = t_split + pk.eps[axis], far_min = t_split - pk.eps[axis];
            const VM<W> active = tmin <= tmax;
            if constexpr (Count) count_visit<W>(active, counters.steps, counters);
            const uint32_t near_high = pk.near_is_high[axis];
            // Per lane as in the scalar kernel: near needed unless near_max < tmin, far needed
            // unless far_min > tmax; a lane in the split plane (NaN t_split) fails every
            // comparison, so it needs both, and min/max below keep its interval unchanged.
            const VM<W> need_near = active & ~(near_max < tmin);
            const VM<W> need_far = active & ~(far_min > tmax);
            const bool go_near = simd::any<W>(need_near), go_far = simd::any<W>(need_far);
            // One side only is the common case: tested first, the far child's index made only
            // where it is needed.
            if (!go_far) {
                if (!go_near) break;  // no live lane here: go to the stack
                node_index = node.first_child() + near_high;
            } else if (!go_near) {
                node_index = node.first_child() + (near_high ^ 1u);
            } else {
                StackEntry<W>& e = stack[stack_size++];
                e.tmin = simd::max<W>(far_min, tmin);
                e.tmax = tmax;
                e.node = node.first_child() + (near_high ^ 1u);
                tmax = simd::min<W>(near_max, tmax);
                node_index = node.first_child() + near_high;
            }
            node = nodes[node_index];
        }
        if (node.is_leaf()) {
            VM<W> active = (tmin <= tmax) & ~done;
            if constexpr (Count) count_visit<W>(active, counters.leaves, counters);
            const uint32_t end = node.first_ref() + node.prim_count();
            // A leaf reached by few live lanes: each lane tests the leaf four triangles at a
            // time (the single-ray kernel's leaf test) when that costs less than one packet
            // test per triangle. Same per-lane arithmetic, same answers. A lane's pass costs
            // about one per-lane-frame packet test, but 2.6 of the uniform frame's (callgrind,
            // bunny 256^2, AVX2: ~180 against ~70 instructions); in effect a uniform packet
            // takes this path when one lane is live and the leaf has three or more triangles.
            uint32_t r = node.first_ref();
            // Closest hit asks for every triangle line of the leaf as soon as its references
            // arrive, instead of each when its test starts: a leaf has 9.4 references on 16
            // bunnies, and the core's window holds about four 70-instruction tests, so the later
            // triangles' loads started late (tests/bench/README.md, session 27, leafchain: 64
            // bunnies' primary rays +11%, 16 bunnies' +3-6%). Not where the lines would often go
            // unused: any hit stops at its first hit, and the mailbox's walk skips the repeats
            // (the stadium, a quarter of its tests, was 3-9% slower with it).
            if constexpr (!AnyHit && !Mail) {
                for (uint32_t i = r; i < end; ++i) {
                    const TriVerts* const tri = tris + (refs[i] & ~KdTree::kLastRef);
                    __builtin_prefetch(tri);  // 36 bytes: the first line and the last byte's
                    __builtin_prefetch(reinterpret_cast<const char*>(tri) + sizeof(TriVerts) - 1);
                }
            }
            if constexpr (!Count) {
                const uint32_t live = simd::bits<W>(active);
                const uint32_t n = node.prim_count();
                const uint32_t passes =
                    static_cast<uint32_t>(__builtin_popcount(live)) * ((n + 3) / 4);
                if (uniform_kz < 0 ? passes < n : passes * 8 < n * 3) {
                    done |= leaf_by_lanes<W, AnyHit>(pk, live, refs + r, n, tris, ids, best);
                    r = end;
                }
            }
            // The frame test is chosen once per leaf, not per triangle, and so is the mailbox's
            // part: the packet's first leaf with tests only records them (nothing to look up
            // yet), later leaves look up and record.
            if (r < end) {
                if constexpr (!Mail) {
                    leaf_in_frame<W, AnyHit, Count, kMailNone>(
                        pk, uniform_kx, uniform_ky, uniform_kz, refs, r, end, tris, ids, active,
                        done, best, mailbox, counters);
                } else if (!mailbox_used) {
                    mailbox.clear();
                    mailbox_used = true;
                    leaf_in_frame<W, AnyHit, Count, kMailRecord>(
                        pk, uniform_kx, uniform_ky, uniform_kz, refs, r, end, tris, ids, active,
                        done, best, mailbox, counters);
                } else {
                    leaf_in_frame<W, AnyHit, Count, kMailSkip>(
                        pk, uniform_kx, uniform_ky, uniform_kz, refs, r, end, tris, ids, active,
                        done, best, mailbox, counters);
                }
            }
        }
        // Pop the next cell in which some lane is still live: its interval is not empty, it has
        // not been occluded, and it starts no later than the lane's closest hit.
        for (;;) {
            if (stack_size == 0) return done;
            const StackEntry<W>& e = stack[--stack_size];
            VM<W> live = (e.tmin <= e.tmax) & ~done;
            if constexpr (!AnyHit) live &= e.tmin <= best.t;
            if (simd::any<W>(live)) {
                tmin = simd::select<W>(live, e.tmin, simd::broadcast<W>(__builtin_inff()));
                tmax = e.tmax;
                node_index = e.node;
                break;
            }
        }
    }
}

/// Every hit of one packet's rays: traverse_packet's per-lane cell decisions without its cut at
/// the closest hit (each lane visits the leaves multi_hit.cpp's single-ray traversal visits, with
/// the same intervals), each leaf's triangles tested against the lanes live there. (The descent
/// loop is traverse_packet's, written out again: a shared always-inline helper taking the node,
/// index and intervals by reference cost the closest-hit kernel 2.2% more instructions in
/// callgrind on the bunny's diffuse rays.) Lane l's hits
/// with ray tmin <= t <= ray tmax go to raw[l * kPacketHitCapacity + k] while k < the capacity;
/// count[l] (zeroed by the caller) counts them all.
template <int W>
inline void traverse_packet_all(const KdTree& tree, const Packet<W>& pk, Hit* raw,
                                uint32_t* count) {
    const KdNode* nodes = tree.nodes.data();
    const uint32_t* refs = tree.leaf_refs.data();
    const TriVerts* tris = tree.tris.data();
    const uint32_t* ids = tree.tri_ids.data();
    StackEntry<W> stack[kMaxDepth + 1];
    int stack_size = 0;
    VF<W> tmin = pk.tmin, tmax = pk.tmax;
    uint32_t node_index = 0;
    if (simd::none<W>(tmin <= tmax)) return;
    for (;;) {
        KdNode node = nodes[node_index];
        while (!node.is_leaf()) {
            const int axis = node.axis();
            const VF<W> t_split = (node.split() - pk.org[axis]) * pk.inv[axis];
            const VF<W> near_max = t_split + pk.eps[axis], far_min = t_split - pk.eps[axis];
            const VM<W> active = tmin <= tmax;
            const uint32_t near_child = node.first_child() + pk.near_is_high[axis];
            const uint32_t far_child = node.first_child() + (pk.near_is_high[axis] ^ 1u);
            const VM<W> need_near = active & ~(near_max < tmin);
            const VM<W> need_far = active & ~(far_min > tmax);
            const bool go_near = simd::any<W>(need_near), go_far = simd::any<W>(need_far);
            if (go_near && go_far) {
                StackEntry<W>& e = stack[stack_size++];
                e.tmin = simd::max<W>(far_min, tmin);
                e.tmax = tmax;
                e.node = far_child;
                tmax = simd::min<W>(near_max, tmax);
                node_index = near_child;
            } else if (go_near) {
                node_index = near_child;
            } else if (go_far) {
                node_index = far_child;
            } else {
                break;
            }
            node = nodes[node_index];
        }
        if (node.is_leaf()) {
            const VM<W> active = tmin <= tmax;
            const uint32_t end = node.first_ref() + node.prim_count();
            for (uint32_t r = node.first_ref(); r < end; ++r) {
                const uint32_t slot = refs[r] & ~KdTree::kLastRef;
                VF<W> t, u, v;
                VM<W> hit = intersect_triangle_packet<W>(pk, tris[slot], active, t, u, v);
                if (simd::none<W>(hit)) continue;
                hit &= t <= pk.ray_tmax;
                for (uint32_t m = simd::bits<W>(hit); m; m &= m - 1) {
                    const int l = __builtin_ctz(m);
                    const uint32_t k = count[l]++;
                    if (k < kPacketHitCapacity)
                        raw[static_cast<uint32_t>(l) * kPacketHitCapacity + k] =
                            Hit{t[l], ids[slot], u[l], v[l]};
                }
            }
        }
        for (;;) {
            if (stack_size == 0) return;
            const StackEntry<W>& e = stack[--stack_size];
            const VM<W> live = e.tmin <= e.tmax;
            if (simd::any<W>(live)) {
                tmin = simd::select<W>(live, e.tmin, simd::broadcast<W>(__builtin_inff()));
                tmax = e.tmax;
                node_index = e.node;
                break;
            }
        }
    }
}

/// The every-hit kernel's answer to schedule_rays: one octant run W rays at a time, each group as
/// a packet (its raw hits to sink.packet) or as single rays (sink.single), as the policy decides.
template <int W>
struct AllHitsRunTracer {
    const KdTree& tree;
    AllHitsSink& sink;
    Policy policy;
    size_t offset;  ///< of the scheduled rays in the kernel's

    [[gnu::always_inline]] void operator()(const Ray* block, size_t base, const uint16_t* order,
                                           int count) const {
        for (int p = 0; p < count; p += W) {
            const int lanes = count - p < W ? count - p : W;
            const uint16_t* index = &order[p];
            const bool as_packet =
                policy == Policy::kPacket || (policy == Policy::kAuto && packet_pays(lanes, W));
            if (!as_packet) {
                for (int l = 0; l < lanes; ++l) sink.single(sink, offset + base + index[l]);
                continue;
            }
            Packet<W> pk;
            setup_packet<W>(tree, block, index, lanes, pk);
            // Raw storage, not Hit[]: Hit's default member initialisers would clear it all.
            alignas(64) unsigned char storage[sizeof(Hit) * W * kPacketHitCapacity];
            Hit* raw = reinterpret_cast<Hit*>(storage);
            uint32_t n[W] = {};
            traverse_packet_all<W>(tree, pk, raw, n);
            size_t rays[W];
            for (int l = 0; l < lanes; ++l) rays[l] = offset + base + index[l];
            sink.packet(sink, rays, lanes, raw, n);
        }
    }
};

/// PacketKernels::all_hits: schedule_rays's blocks and octant runs (its answers for invalid rays,
/// "not occluded", go to a scratch array: such rays have no hits and reach neither sink call).
template <int W>
void all_hits_rays(const KdTree& tree, const Ray* rays, size_t count, AllHitsSink& sink,
                   Policy policy) {
    TraceCounters counters;
    for (size_t first = 0; first < count; first += kBlockRays) {
        const size_t n = count - first < kBlockRays ? count - first : kBlockRays;
        uint8_t unused[kBlockRays];
        schedule_rays<true>(tree, rays + first, n, nullptr, unused, counters,
                            AllHitsRunTracer<W>{tree, sink, policy, first});
    }
}

/// One ray through the single-ray kernel compiled for this ISA; its answer into hits[at] (or
/// occluded[at]).
template <bool AnyHit, bool Count>
[[gnu::always_inline]] inline void trace_single(const KdTree& tree, const Ray& ray, size_t at,
                                                Hit* hits, uint8_t* occluded,
                                                TraceCounters& counters) {
    if constexpr (AnyHit) {
        occluded[at] =
            (Count ? wide_occluded_counted(tree, ray, counters) : wide_occluded(tree, ray)) ? 1 : 0;
    } else {
        hits[at] = Count ? wide_intersect_counted(tree, ray, counters) : wide_intersect(tree, ray);
    }
}

/// The triangle (tree slot) that occluded a lane of this thread's last any-hit packet with an
/// occluded lane on `tree`: a shadow cache (Haines and Greenberg 1986). Rays towards one light
/// that start close together are mostly occluded by the same triangle (the stadium inside: every
/// shadow ray occluded, 2.5 leaves and 6.7 triangle tests a ray to find it), so each any-hit
/// packet first tests its lanes against that triangle, and a lane it occludes does not walk.
/// Exact: a lane is occluded when some triangle of the tree hits it with ray tmin <= t <= ray
/// tmax, as the walk's leaf tests decide it (the walk visits every leaf holding such a hit, and
/// the leaf test is this test: the scalar kernel equals the brute-force oracle), so testing one
/// more triangle of the tree first changes no answer. Any slot below the tree's triangle count is
/// such a triangle, so an entry left by another tree at the same address is safe too.
///
/// The test costs about one packet triangle test a packet, which rays that are seldom occluded
/// (the bunny's, diplodocus', 16 bunnies' shadow sets: 7-8%) do not win back: a lane caught
/// saves the walk only the nodes and leaves it alone needed. So it runs while it pays, measured
/// per thread as mailbox_pays measures the mailbox: always for the first kCacheWarmUp live lanes,
/// then while it catches at least 1/kCachePaysShare of the live lanes it tests, else one packet
/// in kCacheSampleGap + 1 to keep measuring (the counts halve as they grow, so they follow the
/// rays). The choice changes no answer, only the work.
struct OccluderCache {
    static constexpr uint32_t kCacheWarmUp = 4096, kCachePaysShare = 8, kCacheWindow = 1u << 16,
                              kCacheSampleGap = 63;
    const KdTree* tree = nullptr;
    uint32_t slot = kNoHit;  ///< kNoHit: none yet
    uint32_t live = 0;       ///< live lanes tested against the cached triangle (halved as it grows)
    uint32_t caught = 0;     ///< of those, the lanes it occluded
    uint32_t skip = 0;       ///< packets to go untested before the next test
    /// Whether this packet tests the cached triangle (there is one, and the test pays or is due).
    [[nodiscard]] bool due() {
        if (slot == kNoHit) return false;
        if (skip == 0) return true;
        --skip;
        return false;
    }
    /// A test's live lanes and the lanes it caught.
    void count(uint32_t live_lanes, uint32_t caught_lanes) {
        live += live_lanes;
        caught += caught_lanes;
        if (live >= kCacheWindow) {
            live >>= 1;
            caught >>= 1;
        }
        const bool pays = live < kCacheWarmUp || caught * kCachePaysShare >= live;
        skip = pays ? 0 : kCacheSampleGap;
    }
};

/// This thread's OccluderCache for `tree` (a fresh one for another tree).
inline OccluderCache& occluder_cache(const KdTree& tree) {
    static thread_local OccluderCache cache;
    if (cache.tree != &tree || (cache.slot != kNoHit && cache.slot >= tree.tris.size()))
        cache = {.tree = &tree};
    return cache;
}

/// Any hit: the packet's live lanes that the cached occluder hits (the leaf test's arithmetic and
/// its ray tmin <= t <= ray tmax), taken out of the walk (empty intervals).
template <int W>
[[gnu::always_inline]] inline VM<W> occluded_by_cache(const KdTree& tree, uint32_t slot,
                                                      Packet<W>& pk) {
    VF<W> t, u, v;
    VM<W> hit = intersect_triangle_packet<W>(pk, tree.tris[slot], pk.tmin <= pk.tmax, t, u, v);
    if (simd::none<W>(hit)) return hit;
    hit &= t <= pk.ray_tmax;
    pk.tmin = simd::select<W>(hit, simd::broadcast<W>(__builtin_inff()), pk.tmin);
    pk.tmax = simd::select<W>(hit, simd::broadcast<W>(-__builtin_inff()), pk.tmax);
    return hit;
}

/// Traces block[index[0..lanes)] as one packet; answers at hits / occluded [base + index[l]].
/// `occluders`: the thread's OccluderCache for the tree (any hit without Count; else unused).
template <int W, bool AnyHit, bool Count>
[[gnu::always_inline]] inline void trace_packet(const KdTree& tree, const Ray* block, size_t base,
                                                const uint16_t* index, int lanes, Hit* hits,
                                                uint8_t* occluded, OccluderCache* occluders,
                                                TraceCounters& counters) {
    Packet<W> pk;
    setup_packet<W>(tree, block, index, lanes, pk);
    PacketHits<W> best;
    best.t = pk.ray_tmax;
    best.u = simd::broadcast<W>(0.0f);
    best.v = simd::broadcast<W>(0.0f);
    best.prim = simd::broadcast_u<W>(kNoHit);
    VM<W> occ;
    if (!AnyHit && mailbox_pays(counters)) {
        occ = traverse_packet<W, AnyHit, Count, !AnyHit>(tree, pk, best, counters);
    } else if (AnyHit && !Count) {
        // The counting kernels walk every lane (their counts stay the walk's).
        OccluderCache& cache = *occluders;
        VM<W> cached = simd::broadcast_i<W>(0);
        if (cache.due()) {
            const uint32_t live = simd::bits<W>(pk.tmin <= pk.tmax);
            cached = occluded_by_cache<W>(tree, cache.slot, pk);
            cache.count(static_cast<uint32_t>(__builtin_popcount(live)),
                        static_cast<uint32_t>(__builtin_popcount(simd::bits<W>(cached))));
        }
        const VM<W> walked = traverse_packet<W, AnyHit, Count, false>(tree, pk, best, counters);
        if (const uint32_t m = simd::bits<W>(walked)) cache.slot = best.prim[__builtin_ctz(m)];
        occ = cached | walked;
    } else {
        occ = traverse_packet<W, AnyHit, Count, false>(tree, pk, best, counters);
    }
    ++counters.packets;
    counters.packet_rays += static_cast<uint64_t>(lanes);
    if constexpr (AnyHit) {
        const uint32_t mask = simd::bits<W>(occ);
        for (int l = 0; l < lanes; ++l) occluded[base + index[l]] = (mask >> l) & 1u;
    } else {
        store_hits<W>(best, index, lanes, base, hits);
    }
}

/// Traces `count` rays of one octant, block[order[0..count)], W at a time: each group as a packet
/// or as single rays (the policy).
template <int W, bool AnyHit, bool Count>
[[gnu::always_inline]] inline void trace_run(const KdTree& tree, const Ray* block, size_t base,
                                             const uint16_t* order, int count, Hit* hits,
                                             uint8_t* occluded, Policy policy,
                                             TraceCounters& counters) {
    OccluderCache* occluders = nullptr;  // looked up once a run
    if constexpr (AnyHit && !Count) occluders = &occluder_cache(tree);
    for (int p = 0; p < count; p += W) {
        const int lanes = count - p < W ? count - p : W;
        const uint16_t* index = &order[p];
        const bool as_packet = policy == Policy::kPacket || packet_pays(lanes, W);
        if (!as_packet) {
            for (int l = 0; l < lanes; ++l)
                trace_single<AnyHit, Count>(tree, block[index[l]], base + index[l], hits, occluded,
                                            counters);
            counters.single_rays += static_cast<uint64_t>(lanes);
            continue;
        }
        trace_packet<W, AnyHit, Count>(tree, block, base, index, lanes, hits, occluded, occluders,
                                       counters);
    }
}

/// Traces `count` rays in the order schedule_rays picks; answers in input order.
/// How many single rays a batch walks in turn (trace_in_turn). A ray's walk is one chain of
/// dependent loads (wide node, then the next, then a leaf's references and triangles); walks of
/// different rays are independent, so the core overlaps their loads. Measured on the bunny's
/// 1024² sets, `--mode single`, 1 thread, 4 alternated rounds (tests/bench/README.md), medians
/// against one walk at a time: 2 walks +12-25%, 4 walks +21-43%. With each walk's next line
/// prefetched as it moves (prefetch_cell), more walks pay on big trees, whose lines come from the
/// last-level cache or memory: on 16 and 64 bunnies' random rays 8 and 16 walks gave +35-40%
/// over 4 without the prefetch (16 a little ahead of 8, within the noise), the bunny unchanged.
/// Re-tuned after session 19's faster AVX-512 decode (`--mode single`, 2 threads, alternated,
/// tests/bench/README.md, session 20): 12 walks against 16, bunny diffuse 5.94 -> 6.50 Mrays/s,
/// random 8.66 -> 8.94; 16 bunnies diffuse 4.31 -> 4.68, random 5.12 -> 5.35; 64 bunnies
/// diffuse 3.65 -> 3.81, random unchanged; 8 walks within 1% of 12 on the bunny.
inline constexpr int kWalksInTurn = 12;

/// A batch of single rays, K at a time: the walks advance in turn, one cell each, so that one
/// ray's dependent loads overlap the others' work. After a step, the line of the cell the walk
/// moved to is prefetched: it loads while the other K - 1 walks step, instead of when this walk's
/// turn comes again. A walk that moved to a leaf spends its next turn prefetching the leaf's
/// first triangles (its references arrived meanwhile) and tests them the turn after, so the
/// triangle loads, which depend on the references, are also overlapped with the other walks.
/// Each walk is the single-ray kernel's (wide_step), so every answer is its answer. A walk that
/// ends takes the batch's next ray.
///
/// The batch's j-th ray is rays[order(j)], its answer hits / occluded [out_base + order(j)].
template <bool AnyHit, int K, class Order>
[[gnu::always_inline]] inline void trace_in_turn(const KdTree& tree, const Ray* rays, size_t count,
                                                 const Order& order, size_t out_base, Hit* hits,
                                                 uint8_t* occluded, TraceCounters& counters) {
    const WideArrays arrays(tree);
    WideWalk walk[K];      // NOLINT(cppcoreguidelines-pro-type-member-init): set by start
    wide::Stack stack[K];  // NOLINT(cppcoreguidelines-pro-type-member-init): written first
    size_t at[K] = {};
    size_t next = 0;
    const auto answer = [&](size_t i, const WideWalk& w) {
        if constexpr (AnyHit)
            occluded[i] = w.found ? 1 : 0;
        else
            hits[i] = to_hit(w.found, w.best);
    };
    // Starts walk k on the next ray that needs one; false when the batch is done.
    const auto start = [&](int k) {
        while (next < count) {
            const size_t j = order(next++);
            const size_t i = out_base + j;
            const Ray& ray = rays[j];
            if (octant_or_invalid(ray) < 0 || tree.bounds.empty()) {
                answer_miss<AnyHit>(i, hits, occluded, counters);
                continue;
            }
            ++counters.single_rays;
            WideWalk& w = walk[k];
            w.best = {ray.tmax, kNoHit, 0.0f, 0.0f};
            w.found = false;
            w.stack_size = 0;
            if (!wide_start<true>(tree, arrays, ray, w.ray, w.cell)) {
                answer(i, w);
                continue;
            }
            at[k] = i;
            return true;
        }
        return false;
    };
    bool live[K];
    bool leaf_next[K] = {};
    int n_live = 0;
    for (int k = 0; k < K; ++k) n_live += (live[k] = start(k)) ? 1 : 0;
    while (n_live > 0) {
        for (int k = 0; k < K; ++k) {
            if (!live[k]) continue;
            WideWalk& w = walk[k];
            if (leaf_next[k]) {
                prefetch_leaf_triangles(arrays, w.cell.slot);
                leaf_next[k] = false;
                continue;
            }
            if (wide_step<AnyHit>(arrays, w.ray, stack[k], w.stack_size, w.cell, w.best, w.found,
                                  NoCount{})) {
                answer(at[k], w);
                live[k] = start(k);
                if (!live[k]) --n_live;
            } else {
                prefetch_cell(arrays, w.cell.slot);
                leaf_next[k] = WideNode::slot_tag(w.cell.slot) == WideNode::kSlotLeaf;
            }
        }
    }
}

/// The time stamp counter, read after the work before it and before the work after it.
[[gnu::always_inline]] inline uint64_t cycles() {
    asm volatile("" ::: "memory");
    _mm_lfence();
    const uint64_t t = __rdtsc();
    _mm_lfence();
    asm volatile("" ::: "memory");
    return t;
}

/// What the auto policy has measured of two ways to trace a block, on this thread, for one
/// tree, query kind and choice (CostSlot: packets or single rays for incoherent or coherent
/// blocks, sorted or unsorted packets for coherent any-hit ones).
struct IncoherentCosts {
    const KdTree* tree = nullptr;   ///< with its nodes' address: a tree built where one was
    const KdNode* nodes = nullptr;  ///< destroyed is most likely told apart
    /// The last three measurements (0: none) of the second way's time per ray over the first's
    /// (single rays over packets; unsorted packets over sorted ones), newest first; their median
    /// decides, so one that the operating system interrupted does not.
    float ratio[3] = {0.0f, 0.0f, 0.0f};
    uint32_t until_measure = 0;  ///< blocks to go the faster way before the next measured one
    bool second_first = false;   ///< the next measured block's first half goes the second way
    /// A measurement over two blocks (RunTracer::sort_measured): the first block's time per ray,
    /// 0 when none is pending, and where the block after it starts (the second must be that one).
    float first_ticks = 0.0f;
    const Ray* next_block = nullptr;

    /// The median of three measurements, newest first (0: none; of two, their mean).
    [[nodiscard]] static float median_of(const float (&m)[3]) {
        const float a = m[0], b = m[1], c = m[2];
        if (c == 0.0f) return b == 0.0f ? a : 0.5f * (a + b);
        return a < b ? (b < c ? b : (a < c ? c : a)) : (a < c ? a : (b < c ? c : b));
    }
    /// The median of the ratios measured so far (0: none).
    [[nodiscard]] float median() const { return median_of(ratio); }

    /// Adds a measurement (the second way's time per ray over the first's) and sets the gap to
    /// the next one (kMeasureBase, times `gap_scale`).
    void record(float r, float gap_scale = 1.0f);
};

/// After a measured block, where the slower way took r times as long as the faster (the
/// median of the last three), the next kMeasureBase * r^2 blocks go the faster way; then one is
/// measured again (the rays may change kind part of the way through a batch, or from batch to
/// batch). Half a measured block goes the slower way, so measuring costs at most
/// (r - 1) / (2 kMeasureBase r^2) of the time: 1/128 at r = 2, less either side. Until three
/// measurements are in, every kMeasureFirstGap-th block is measured.
inline constexpr float kMeasureBase = 16.0f;
inline constexpr float kMeasureMaxGap = 1024.0f;
inline constexpr uint32_t kMeasureFirstGap = 4;
/// A block of fewer rays is not measured (its halves would time too little work).
inline constexpr int kMeasureMinRays = 512;

inline void IncoherentCosts::record(float r, float gap_scale) {
    ratio[2] = ratio[1];
    ratio[1] = ratio[0];
    ratio[0] = r;
    if (ratio[2] == 0.0f) {
        until_measure = kMeasureFirstGap;
    } else {
        const float m = median();
        const float slower = m < 1.0f ? 1.0f / m : m;
        const float gap = gap_scale * kMeasureBase * slower * slower;
        until_measure = static_cast<uint32_t>(gap < kMeasureMaxGap ? gap : kMeasureMaxGap);
    }
}

/// The choices the auto policy measures, each in cost slots of its own (incoherent_costs): packets
/// against single rays for incoherent blocks and for coherent ones (whose costs differ and must
/// not mix), and, for coherent any-hit blocks, sorted packets against unsorted ones.
enum class CostSlot { kIncoherent, kCoherent, kCoherentSort };

/// A measurement of the sort (RunTracer::sort_measured) takes two whole blocks, one each way, so
/// it costs a whole block the slower way rather than half of one: its gaps are twice as long.
inline constexpr float kSortGapScale = 2.0f;

/// This thread's measurements for `tree` (closest hit or any hit; one CostSlot): a small table by
/// the tree's address, so that a scene's rounds, which go from one instance's tree to the next,
/// keep each tree's measurements; a tree that takes another's slot starts afresh.
inline constexpr int kCostSlotBits = 4;

template <bool AnyHit, CostSlot Slot>
IncoherentCosts& incoherent_costs(const KdTree& tree) {
    static thread_local IncoherentCosts slots[1 << kCostSlotBits];
    const uint64_t key = reinterpret_cast<uintptr_t>(&tree) * 0x9E3779B97F4A7C15ull;
    IncoherentCosts& costs = slots[key >> (64 - kCostSlotBits)];
    if (costs.tree != &tree || costs.nodes != tree.nodes.data())
        costs = IncoherentCosts{.tree = &tree, .nodes = tree.nodes.data()};
    return costs;
}

/// Whether the auto policy measures coherent blocks (RunTracer::coherent_block), by query kind.
template <bool AnyHit>
inline constexpr bool kMeasureCoherent = AnyHit;

/// The kernel's answer to schedule_rays: traces one octant run W rays at a time (trace_run), and
/// under the auto policy chooses how to trace an incoherent block (incoherent_block) and a coherent
/// any-hit one (coherent_block). A struct rather than a lambda: a lambda would not inherit the ISA
/// target.
template <int W, bool AnyHit, bool Count>
struct RunTracer {
    const KdTree& tree;
    Hit* hits;
    uint8_t* occluded;
    Policy policy;
    TraceCounters& counters;

    [[gnu::always_inline]] void operator()(const Ray* block, size_t base, const uint16_t* order,
                                           int count) const {
        trace_run<W, AnyHit, Count>(tree, block, base, order, count, hits, occluded, policy,
                                    counters);
    }

    /// The block's rays walked in turn as single rays, in input order (no sort).
    void singles(const Ray* block, size_t base, int n) const {
        trace_in_turn<AnyHit, kWalksInTurn>(
            tree, block, static_cast<size_t>(n), [](size_t j) { return j; }, base, hits, occluded,
            counters);
    }

    /// An incoherent block (block_is_incoherent; lo, hi its origins' sample bounds). Packets of
    /// sorted rays or single rays walked in turn: which is faster depends on the scene, the rays
    /// and the machine. Packets win when neighbouring rays stay together (short rays that hit a
    /// nearby wall, as inside a room); single rays win when the packets empty out (long rays
    /// through a finely cut model), and they need no sort. So the auto policy measures: on each
    /// thread, per tree and query kind, the time per ray of each way on the two halves of a
    /// measured block (IncoherentCosts); the blocks between measured ones go the faster way
    /// (kMeasureBase says how many). The choice only decides speed: both ways give every ray the
    /// single-ray kernel's answer. The counting kernels keep to packets (their counts stay
    /// reproducible); the test policies kIncoherentAsPacket and kIncoherentAsSingle fix the way,
    /// kIncoherentMeasured measures every block.
    void incoherent_block(const Ray* block, size_t base, int n, const float lo[3],
                          const float hi[3]) const {
        const auto packets = [&](const Ray* rays, size_t at, int m) {
            trace_sorted_block<AnyHit>(tree, rays, at, m, lo, hi, hits, occluded, counters, *this);
        };
        if (Count || policy == Policy::kPacket || policy == Policy::kIncoherentAsPacket) {
            packets(block, base, n);
            return;
        }
        if (policy == Policy::kIncoherentAsSingle) {
            singles(block, base, n);
            return;
        }
        measured<CostSlot::kIncoherent>(block, base, n, packets);
    }

    /// A coherent block (not block_is_incoherent: one origin or one direction, e.g. shadow rays
    /// towards one light) goes in runs of packets. Its packets stay full, but on a big tree they
    /// may still lose to single rays walked in turn for any hit (2 threads, 64 bunnies' shadow
    /// set: single rays 5.7 Mrays/s, packets 4.8), while on smaller trees packets win (16
    /// bunnies: 7.8 against 6.1). So for any hit the auto policy measures the two ways as for an
    /// incoherent block, in cost slots of their own (CostSlot::kCoherent). Any hit's packets go
    /// either in input order, in runs of kCoherentRun rays (trace_coherent_block), or sorted by
    /// where the rays start across their common way (trace_origin_sorted_block: in image order a
    /// packet is a strip of one row; sorted, a small patch, whose rays stay together longer: 16
    /// bunnies' shadow set 7.7 -> 9.4 Mrays/s). The sort costs about 150 instructions and two L1
    /// misses per ray, which cheap packets do not win back (the stadium's shadow set: 86 -> 44
    /// Mrays/s sorted, its packets' node visits unchanged; tests/bench/README.md). So that choice
    /// is measured too (sort_measured, CostSlot::kCoherentSort), on blocks that go as packets
    /// when no measurement against single rays is due. Closest-hit blocks (primary rays) keep to
    /// packets in input order, as do the counting kernels and the fixed test policies;
    /// kIncoherentMeasured measures every coherent any-hit block against single rays (its packets
    /// as the sort slot says), kCoherentSortMeasured every one sorted against unsorted, and
    /// kCoherentSorted sorts every one. Every way gives every ray the single-ray kernel's answer.
    void coherent_block(const Ray* block, size_t base, int n) const {
        const auto packets = [&](const Ray* rays, size_t at, int m) { image_block(rays, at, m); };
        const auto sorted = [&](const Ray* rays, size_t at, int m) {
            trace_origin_sorted_block<AnyHit>(tree, rays, at, m, hits, occluded, counters, *this);
        };
        if (AnyHit && !Count && policy == Policy::kCoherentSorted) {
            sorted(block, base, n);
            return;
        }
        if (AnyHit && !Count && policy == Policy::kCoherentPairMeasured) {
            sorted_pair_measured(block, base, n);
            return;
        }
        if (AnyHit && !Count && policy == Policy::kCoherentSortMeasured) {
            sort_measured(block, base, n, incoherent_costs<AnyHit, CostSlot::kCoherentSort>(tree));
            return;
        }
        if (Count || !kMeasureCoherent<AnyHit> ||
            (policy != Policy::kAuto && policy != Policy::kIncoherentMeasured)) {
            packets(block, base, n);
            return;
        }
        IncoherentCosts& by_sort = incoherent_costs<AnyHit, CostSlot::kCoherentSort>(tree);
        if (policy == Policy::kAuto && n >= kMeasureMinRays &&
            (by_sort.until_measure == 0 || by_sort.first_ticks != 0.0f)) {
            // The sort is measured where no measurement against single rays is due (or the
            // measurement's first block went already). While single rays are the faster way,
            // only until it has its three measurements: single rays may have won against
            // unsorted packets only, and sorted ones may beat them (16 bunnies' shadow set:
            // single rays over unsorted packets 0.65-0.99, over sorted ones 1.42-1.59); once
            // known, a measurement there costs two blocks of packets and changes nothing (64
            // bunnies). Where the sort's answer changes which packets go, the measurements
            // against single rays were of the other packets: they start afresh.
            IncoherentCosts& costs = incoherent_costs<AnyHit, CostSlot::kCoherent>(tree);
            const float ratio = costs.median();
            const bool singles_win = ratio != 0.0f && ratio < 1.0f;
            if (by_sort.first_ticks != 0.0f ||
                (costs.until_measure > 0 && (!singles_win || by_sort.ratio[2] == 0.0f))) {
                if (costs.until_measure > 0) --costs.until_measure;
                const bool was_sorted = by_sort.median() > 1.0f;
                sort_measured(block, base, n, by_sort);
                if ((by_sort.median() > 1.0f) != was_sorted)
                    costs = IncoherentCosts{.tree = costs.tree, .nodes = costs.nodes};
                return;
            }
        } else if (by_sort.until_measure > 0) {
            --by_sort.until_measure;
        }
        // Packets are measured against single rays as they trace: sorted ones on two whole
        // neighbouring blocks (sorted_pair_measured), unsorted ones in runs of kCoherentRun
        // rays each way in turn.
        if (by_sort.median() > 1.0f) {
            const IncoherentCosts& costs = incoherent_costs<AnyHit, CostSlot::kCoherent>(tree);
            if (policy == Policy::kAuto &&
                (costs.first_ticks != 0.0f || (n >= kMeasureMinRays && costs.until_measure == 0))) {
                sorted_pair_measured(block, base, n);
                return;
            }
            measured<CostSlot::kCoherent>(block, base, n, sorted, true);
        } else {
            measured<CostSlot::kCoherent>(block, base, n, packets, false);
        }
    }

    /// A coherent block's rays in runs of packets (trace_coherent_block), or in square patches
    /// when they are an image's rows from one point (image_row, trace_patch_block). The row
    /// length found is kept per thread and tried first on the next block; after a block of one
    /// origin whose rows were not found, kRowSearchGap such blocks go in input order unsearched.
    void image_block(const Ray* block, size_t base, int n) const {
        static thread_local int row_guess = 0;
        static thread_local int search_gap = 0;
        int row = 0;
        if (search_gap > 0 && !rows_of(block, n, row_guess)) {
            --search_gap;
        } else {
            row = image_row(block, n, row_guess);
            if (row > 0)
                row_guess = row;
            else if (n >= 4 && ends_share_origin(block, n))
                search_gap = kRowSearchGap;
        }
        if (row > 0)
            trace_patch_block<W, AnyHit>(block, base, n, row, hits, occluded, counters, *this);
        else
            trace_coherent_block<AnyHit>(block, base, n, hits, occluded, counters, *this);
    }

    /// A coherent any-hit block measured one of the two ways its packets may go: sorted by
    /// origin (trace_origin_sorted_block) or in input order (trace_coherent_block). A
    /// measurement takes two blocks in a row, one each way, the order swapping from one
    /// measurement to the next; the ratio of their times per ray (unsorted over sorted) goes to
    /// `by_sort` (CostSlot::kCoherentSort). Whole blocks, not halves: the sort pays through the
    /// patches it makes across a block's rows, and a half block (fewer rows) makes worse ones
    /// (16 bunnies' shadow set: halves measured unsorted / sorted at about 1.02, every block
    /// forced one way or the other 1.13-1.23; tests/bench/README.md). A coherent block's rays
    /// are in image order, so two neighbouring blocks are neighbouring rows of about the same
    /// cost; the two blocks must be neighbours in the batch.
    void sort_measured(const Ray* block, size_t base, int n, IncoherentCosts& by_sort) const {
        const auto sorted = [&](const Ray* rays, size_t at, int m) {
            trace_origin_sorted_block<AnyHit>(tree, rays, at, m, hits, occluded, counters, *this);
        };
        const auto unsorted = [&](const Ray* rays, size_t at, int m) { image_block(rays, at, m); };
        pair_measured(block, base, n, by_sort, sorted, unsorted, kSortGapScale);
    }

    /// A coherent any-hit block measured as sorted packets (trace_origin_sorted_block) or as
    /// single rays walked in turn (CostSlot::kCoherent: single rays over packets), one whole
    /// block each way (pair_measured), not a block's halves: the sort pays through the patches it
    /// makes across a whole block's rows (see sort_measured). On a block's halves, 16 bunnies'
    /// shadow set measured about as it does against unsorted packets (single rays ahead).
    void sorted_pair_measured(const Ray* block, size_t base, int n) const {
        const auto sorted = [&](const Ray* rays, size_t at, int m) {
            trace_origin_sorted_block<AnyHit>(tree, rays, at, m, hits, occluded, counters, *this);
        };
        const auto single_rays = [&](const Ray* rays, size_t at, int m) { singles(rays, at, m); };
        pair_measured(block, base, n, incoherent_costs<AnyHit, CostSlot::kCoherent>(tree), sorted,
                      single_rays, kSortGapScale);
    }

    /// One block of a measurement over two neighbouring whole blocks, one traced `first`'s way,
    /// the other `second`'s, the order swapping from one measurement to the next; the ratio of
    /// their times per ray (second over first) goes to `costs` (its gap scaled by `gap_scale`).
    /// A pending first block that is not this one's neighbour (the thread took a block from
    /// elsewhere in the batch, or another batch) is dropped: blocks far apart in an image cost up
    /// to 13 times as much as each other (16 bunnies' shadow set, 2 threads).
    template <class First, class Second>
    void pair_measured(const Ray* block, size_t base, int n, IncoherentCosts& costs,
                       const First& first, const Second& second, float gap_scale) const {
        if (costs.next_block != block) costs.first_ticks = 0.0f;
        costs.next_block = block + n;
        const bool first_of_two = costs.first_ticks == 0.0f;
        // second_first: this measurement's first block goes the second way.
        const bool second_way = first_of_two == costs.second_first;
        const uint64_t t0 = cycles();
        if (second_way)
            second(block, base, n);
        else
            first(block, base, n);
        const uint64_t t1 = cycles();
        if (t1 <= t0) {  // a clock that stood still or went back: start again
            costs.first_ticks = 0.0f;
            return;
        }
        const float ticks = static_cast<float>(t1 - t0) / static_cast<float>(n);
        if (first_of_two) {
            costs.first_ticks = ticks;
            return;
        }
        const float ratio = second_way ? ticks / costs.first_ticks : costs.first_ticks / ticks;
        costs.first_ticks = 0.0f;
        costs.second_first = !costs.second_first;
        costs.record(ratio, gap_scale);
    }

    /// Traces block[0, n) half one way, half the other (`second_first`: the first half goes the
    /// second way); true, with the second way's time per ray over the first's in `ratio`, unless
    /// the clock stood still or went back.
    template <class First, class Second>
    bool time_halves(const Ray* block, size_t base, int n, bool second_first, const First& first,
                     const Second& second, float& ratio) const {
        const int half = n / 2;
        const uint64_t t0 = cycles();
        if (second_first)
            second(block, base, half);
        else
            first(block, base, half);
        const uint64_t t1 = cycles();
        if (second_first)
            first(block + half, base + static_cast<size_t>(half), n - half);
        else
            second(block + half, base + static_cast<size_t>(half), n - half);
        const uint64_t t2 = cycles();
        if (t1 <= t0 || t2 <= t1) return false;
        const float a = static_cast<float>(t1 - t0) / static_cast<float>(half);
        const float b = static_cast<float>(t2 - t1) / static_cast<float>(n - half);
        ratio = second_first ? a / b : b / a;
        return true;
    }

    /// The measured choice between `packets` and single rays for one block (IncoherentCosts of
    /// the block's kind): the faster way so far, or, for a measured block, half each way: its
    /// two halves (`halves`), or its runs of kCoherentRun rays each way in turn.
    template <CostSlot Slot, class Packets>
    void measured(const Ray* block, size_t base, int n, const Packets& packets,
                  bool halves = Slot == CostSlot::kIncoherent) const {
        IncoherentCosts& costs = incoherent_costs<AnyHit, Slot>(tree);
        const bool measure = policy == Policy::kIncoherentMeasured
                                 ? n >= 2
                                 : n >= kMeasureMinRays && costs.until_measure == 0;
        if (!measure) {
            if (costs.until_measure > 0) --costs.until_measure;
            const float ratio = costs.median();
            if (ratio != 0.0f && ratio < 1.0f)
                singles(block, base, n);
            else
                packets(block, base, n);
            return;
        }
        const bool singles_first = costs.second_first;
        costs.second_first = !singles_first;
        const auto single_rays = [&](const Ray* rays, size_t at, int m) { singles(rays, at, m); };
        float ratio = 0.0f;
        if (!halves && n >= 2 * kCoherentRun) {
            // A coherent block's rays are in image order: its two halves are different parts
            // of the image and may cost differently whichever way they go. So its runs of
            // kCoherentRun rays go each way in turn, the two ways' rays spread over the block.
            uint64_t t[2] = {0, 0};  // [0] packets, [1] single rays
            int m[2] = {0, 0};
            for (int first = 0, k = 0; first < n; first += kCoherentRun, ++k) {
                const int len = n - first < kCoherentRun ? n - first : kCoherentRun;
                const int way = ((k & 1) == 0) == singles_first ? 1 : 0;
                const Ray* run = block + first;
                const size_t at = base + static_cast<size_t>(first);
                const uint64_t t0 = cycles();
                if (way == 1)
                    singles(run, at, len);
                else
                    packets(run, at, len);
                const uint64_t t1 = cycles();
                t[way] += t1 > t0 ? t1 - t0 : 0;
                m[way] += len;
            }
            if (t[0] == 0 || t[1] == 0) return;  // a clock that stood still or went back
            ratio = (static_cast<float>(t[1]) / static_cast<float>(m[1])) /
                    (static_cast<float>(t[0]) / static_cast<float>(m[0]));
        } else {
            // A measured block: one half each way, the halves' roles swapping from one measured
            // block to the next (the first half is traced first).
            if (!time_halves(block, base, n, singles_first, packets, single_rays, ratio)) return;
        }
        costs.record(ratio);
    }
};

template <int W, bool AnyHit, bool Count>
void trace_rays(const KdTree& tree, const Ray* rays, size_t count, Hit* hits, uint8_t* occluded,
                Policy policy, TraceCounters& counters) {
    if (policy == Policy::kSingle) {
        if constexpr (!Count) {
            // The counting kernels below count the same walks one ray at a time.
            trace_in_turn<AnyHit, kWalksInTurn>(
                tree, rays, count, [](size_t j) { return j; }, 0, hits, occluded, counters);
            return;
        }
        // Single rays need no octant runs: each is traced in input order, without the sort the
        // packets' grouping needs (the single-ray kernel answers invalid rays as misses itself).
        for (size_t i = 0; i < count; ++i) {
            if (octant_or_invalid(rays[i]) < 0 || tree.bounds.empty()) {
                answer_miss<AnyHit>(i, hits, occluded, counters);
                continue;
            }
            trace_single<AnyHit, Count>(tree, rays[i], i, hits, occluded, counters);
            ++counters.single_rays;
        }
        return;
    }
    schedule_rays<AnyHit>(tree, rays, count, hits, occluded, counters,
                          RunTracer<W, AnyHit, Count>{tree, hits, occluded, policy, counters});
}

/// The kernels of PacketKernels; Count selects the counting copies (TraceOptions::count_work).
template <int W, bool Count>
void intersect_rays(const KdTree& tree, const Ray* rays, size_t count, Hit* hits, Policy policy,
                    TraceCounters& counters) {
    trace_rays<W, false, Count>(tree, rays, count, hits, nullptr, policy, counters);
}

template <int W, bool Count>
void occluded_rays(const KdTree& tree, const Ray* rays, size_t count, uint8_t* occluded,
                   Policy policy, TraceCounters& counters) {
    trace_rays<W, true, Count>(tree, rays, count, nullptr, occluded, policy, counters);
}

// ---------------------------------------------------------------------------------------------
// A caller's packet (LaneKernels, packet.h): a scene's depth-first walk carries the lanes of its
// top-level packet that reach an instance into the instance's tree at once.

/// A caller's packet with this many active lanes or fewer (of one octant) goes as single rays: a
/// packet's node visit costs about as much as two single rays' steps, so it pays from three live
/// lanes (Embree's coherent switch, two lanes, in effect).
constexpr int kLaneSingleMax = 2;

/// The lanes of `mask` by the octant of their rays (a packet needs one: Packet::near_is_high),
/// each octant's lanes ascending in by_octant[o][0..size[o]); each invalid ray is answered as the
/// single-ray kernel answers it (no hit) by miss(lane). Returns the octants present (bit o).
template <class Miss>
[[gnu::always_inline]] inline uint32_t lanes_by_octant(const Ray* rays, uint32_t mask,
                                                       uint16_t (*by_octant)[kLaneRays], int* size,
                                                       Miss&& miss) {
    uint32_t present = 0;
    for (uint32_t m = mask; m; m &= m - 1) {
        const int l = __builtin_ctz(m);
        const int o = octant_or_invalid(rays[l]);
        if (o < 0) {
            miss(l);
            continue;
        }
        if (!(present >> o & 1u)) size[o] = 0;
        present |= 1u << o;
        by_octant[o][size[o]++] = static_cast<uint16_t>(l);
    }
    return present;
}

/// LaneKernels' work with W-lane packets (W <= kLaneRays): the valid lanes of `mask`, per octant,
/// W at a time, through setup_packet and traverse_packet (per lane the single-ray kernel's
/// decisions), or through the single-ray kernel where few are live. Closest hit: answers into
/// hits[lane]; any hit: returns the lanes occluded. Lanes outside `mask` are not touched.
template <int W, bool AnyHit>
uint32_t lanes_trace(const KdTree& tree, const Ray* rays, uint32_t mask, Hit* hits) noexcept {
    uint16_t by_octant[8][kLaneRays];
    int size[8];
    uint32_t present = lanes_by_octant(rays, mask, by_octant, size, [&](int l) {
        if constexpr (!AnyHit) hits[l] = Hit{};
    });
    uint32_t occ = 0;
    TraceCounters unused;
    for (; present; present &= present - 1) {
        const int o = __builtin_ctz(present);
        const uint16_t* index = by_octant[o];
        const int count = size[o];
        if (count <= kLaneSingleMax || tree.bounds.empty()) {
            for (int k = 0; k < count; ++k) {
                if constexpr (AnyHit)
                    occ |= (wide_occluded(tree, rays[index[k]]) ? 1u : 0u) << index[k];
                else
                    hits[index[k]] = wide_intersect(tree, rays[index[k]]);
            }
            continue;
        }
        for (int p = 0; p < count; p += W) {
            const int lanes = count - p < W ? count - p : W;
            Packet<W> pk;
            setup_packet<W>(tree, rays, index + p, lanes, pk);
            PacketHits<W> best;
            best.t = pk.ray_tmax;
            best.u = simd::broadcast<W>(0.0f);
            best.v = simd::broadcast<W>(0.0f);
            best.prim = simd::broadcast_u<W>(kNoHit);
            [[maybe_unused]] const uint32_t bits =
                simd::bits<W>(traverse_packet<W, AnyHit, false, false>(tree, pk, best, unused));
            if constexpr (AnyHit) {
                for (int l = 0; l < lanes; ++l) occ |= (bits >> l & 1u) << index[p + l];
            } else {
                store_hits<W>(best, index + p, lanes, 0, hits);
            }
        }
    }
    return occ;
}

template <int W>
void lanes_intersect(const KdTree& tree, const Ray* rays, uint32_t mask, Hit* hits) noexcept {
    lanes_trace<W, false>(tree, rays, mask, hits);
}

template <int W>
uint32_t lanes_occluded(const KdTree& tree, const Ray* rays, uint32_t mask) noexcept {
    return lanes_trace<W, true>(tree, rays, mask, nullptr);
}

}  // namespace
}  // namespace kdrt::detail
