// Internal: the hot steps of a packet's top-level walk (scene_packet.h's TopPacketOps), written
// once and compiled once per instruction set: each including file puts it inside that set's
// `#pragma GCC target` region, in an anonymous namespace (simd.h says why). A packet's eight
// lanes are one AVX2 register (F8, where the including file defines KDRT_SCENE_STEPS_AVX2) or two
// SSE halves (Halves). Per lane
// it is TopWalk's arithmetic and order exactly: the same plane and box tests on the same floats (no
// FMA: -ffp-contract=off and no fma target), the same cells in the same order, and a lane leaves
// each cell that starts beyond its limit, so a lane reaches the leaves (and the instances) its own
// TopWalk would reach.

#pragma once

#include <immintrin.h>

#include <cstddef>
#include <cstdint>
#include <cstring>

#include "scene_internal.h"
#include "scene_packet.h"

// The helpers take and return 32-byte vectors; at the baseline (no AVX) GCC warns that such a
// function's ABI differs between targets. They have internal linkage, so no call crosses targets
// (as wide_kernel.h; the setting stays on for the rest of the including translation unit).
#pragma GCC diagnostic ignored "-Wpsabi"

namespace kdrt::detail {
namespace {

/// A packet's eight lanes as two SSE halves (the baseline).
struct Halves {
    F4 h[2];
};

inline Halves load(const Lanes& l, Halves) noexcept { return Halves{{l.h[0], l.h[1]}}; }
inline void store(Lanes& l, const Halves& v) noexcept { l.h[0] = v.h[0], l.h[1] = v.h[1]; }
inline Halves splat(float x, Halves) noexcept { return Halves{{F4{} + x, F4{} + x}}; }
inline Halves operator+(const Halves& a, const Halves& b) noexcept {
    return Halves{{a.h[0] + b.h[0], a.h[1] + b.h[1]}};
}
inline Halves operator-(const Halves& a, const Halves& b) noexcept {
    return Halves{{a.h[0] - b.h[0], a.h[1] - b.h[1]}};
}
inline Halves operator*(const Halves& a, const Halves& b) noexcept {
    return Halves{{a.h[0] * b.h[0], a.h[1] * b.h[1]}};
}
/// a > b ? a : b and a < b ? a : b, lane by lane.
inline Halves take_gt(const Halves& a, const Halves& b) noexcept {
    return Halves{{a.h[0] > b.h[0] ? a.h[0] : b.h[0], a.h[1] > b.h[1] ? a.h[1] : b.h[1]}};
}
inline Halves take_lt(const Halves& a, const Halves& b) noexcept {
    return Halves{{a.h[0] < b.h[0] ? a.h[0] : b.h[0], a.h[1] < b.h[1] ? a.h[1] : b.h[1]}};
}
inline uint32_t bits(I4 lo, I4 hi) noexcept {
    return static_cast<uint32_t>(_mm_movemask_ps(reinterpret_cast<__m128>(lo))) |
           static_cast<uint32_t>(_mm_movemask_ps(reinterpret_cast<__m128>(hi))) << 4;
}
/// Bit i set when a > b, !(a < b), !(a > b), a <= b in lane i.
inline uint32_t gt_bits(const Halves& a, const Halves& b) noexcept {
    return bits(a.h[0] > b.h[0], a.h[1] > b.h[1]);
}
inline uint32_t not_lt_bits(const Halves& a, const Halves& b) noexcept {
    return bits(~(a.h[0] < b.h[0]), ~(a.h[1] < b.h[1]));
}
inline uint32_t not_gt_bits(const Halves& a, const Halves& b) noexcept {
    return bits(~(a.h[0] > b.h[0]), ~(a.h[1] > b.h[1]));
}
inline uint32_t le_bits(const Halves& a, const Halves& b) noexcept {
    return bits(a.h[0] <= b.h[0], a.h[1] <= b.h[1]);
}
inline Halves operator/(const Halves& a, const Halves& b) noexcept {
    return Halves{{a.h[0] / b.h[0], a.h[1] / b.h[1]}};
}
/// |a| lane by lane (the sign bit cleared, as std::fabs).
inline Halves abs(const Halves& a) noexcept {
    const I4 m = I4{} + 0x7fffffff;
    return Halves{{reinterpret_cast<F4>(reinterpret_cast<I4>(a.h[0]) & m),
                   reinterpret_cast<F4>(reinterpret_cast<I4>(a.h[1]) & m)}};
}
inline Halves from_halves(const Halves& a, Halves) noexcept { return a; }

#if KDRT_SCENE_STEPS_AVX2
/// A packet's eight lanes in one AVX2 register.
using F8 = float __attribute__((vector_size(32)));
using I8 = int32_t __attribute__((vector_size(32)));
static_assert(sizeof(Lanes) == sizeof(F8) && alignof(Lanes) >= alignof(F8));

inline F8 load(const Lanes& l, F8) noexcept {
    F8 v;
    std::memcpy(&v, &l, sizeof v);
    return v;
}
inline void store(Lanes& l, F8 v) noexcept { std::memcpy(&l, &v, sizeof v); }
inline F8 splat(float x, F8) noexcept { return F8{} + x; }
inline F8 take_gt(F8 a, F8 b) noexcept { return a > b ? a : b; }
inline F8 take_lt(F8 a, F8 b) noexcept { return a < b ? a : b; }
inline uint32_t bits(I8 m) noexcept {
    return static_cast<uint32_t>(_mm256_movemask_ps(reinterpret_cast<__m256>(m)));
}
inline uint32_t gt_bits(F8 a, F8 b) noexcept { return bits(a > b); }
inline uint32_t not_lt_bits(F8 a, F8 b) noexcept { return bits(~(a < b)); }
inline uint32_t not_gt_bits(F8 a, F8 b) noexcept { return bits(~(a > b)); }
inline uint32_t le_bits(F8 a, F8 b) noexcept { return bits(a <= b); }
inline F8 abs(F8 a) noexcept { return reinterpret_cast<F8>(reinterpret_cast<I8>(a) & 0x7fffffff); }
inline F8 from_halves(const Halves& a, F8) noexcept {
    return reinterpret_cast<F8>(
        _mm256_set_m128(reinterpret_cast<__m128>(a.h[1]), reinterpret_cast<__m128>(a.h[0])));
}
#endif

/// The fields of up to eight rays in lanes, by the Ray layout: ox, oy, oz, tmin, dx, dy, dz, tmax;
/// lane l holds rays[order[l]] (lanes from `count` on repeat lane 0's ray). Two 4 x 4 transposes
/// per half, so no lane is written alone (a vector load of eight single-float stores would wait
/// for them all to leave the store buffer).
inline void ray_lanes(const Ray* rays, const uint16_t* order, int count, Halves field[8]) noexcept {
    static_assert(sizeof(Ray) == 8 * sizeof(float) && offsetof(Ray, dx) == 4 * sizeof(float));
    for (int h = 0; h < 2; ++h) {
        __m128 lo[4], hi[4];
        for (int k = 0; k < 4; ++k) {
            const Ray& r = rays[order[4 * h + k < count ? 4 * h + k : 0]];
            lo[k] = _mm_loadu_ps(&r.ox);
            hi[k] = _mm_loadu_ps(&r.dx);
        }
        _MM_TRANSPOSE4_PS(lo[0], lo[1], lo[2], lo[3]);
        _MM_TRANSPOSE4_PS(hi[0], hi[1], hi[2], hi[3]);
        for (int f = 0; f < 4; ++f) {
            field[f].h[h] = reinterpret_cast<F4>(lo[f]);
            field[4 + f].h[h] = reinterpret_cast<F4>(hi[f]);
        }
    }
}

/// make_top_ray's margin of each lane: float(kMarginScale * kappa_max * (3 mag + 3 size_max)),
/// mag the largest |origin component|, in double as margin() does it (the largest of the floats
/// is exact in double, and the same operations in the same order give the same bits).
inline Halves margin_lanes(const SceneData& s, const Halves& ox, const Halves& oy,
                           const Halves& oz) noexcept {
    using D4 = double __attribute__((vector_size(32)));
    const double scale = kMarginScale * s.kappa_max, size3 = 3.0 * s.size_max;
    Halves out;
    for (int h = 0; h < 2; ++h) {
        F4 mag = reinterpret_cast<F4>(reinterpret_cast<I4>(ox.h[h]) & 0x7fffffff);
        const F4 y = reinterpret_cast<F4>(reinterpret_cast<I4>(oy.h[h]) & 0x7fffffff);
        const F4 z = reinterpret_cast<F4>(reinterpret_cast<I4>(oz.h[h]) & 0x7fffffff);
        mag = y > mag ? y : mag;
        mag = z > mag ? z : mag;
        const D4 m = __builtin_convertvector(mag, D4);
        out.h[h] = __builtin_convertvector(scale * (3.0 * m + size3), F4);
    }
    return out;
}

/// TopPacketOps::next_leaf.
template <class V>
const TopNode* next_leaf_steps(TopPacket& pk, const SceneData& s, const Lanes& limit_lanes,
                               uint32_t& at) noexcept {
    const V limit = load(limit_lanes, V{});
    while (pk.size > 0) {
        const TopPacketCell& cell = pk.stack[--pk.size];
        uint32_t mask = cell.mask & pk.lanes & ~pk.ended;
        if (!mask) continue;
        V tmin = load(cell.tmin, V{}), tmax = load(cell.tmax, V{});
        // Lanes whose cell starts beyond their limit leave this cell only (TopWalk::next_leaf drops
        // such a cell and goes on: a cell below it on the stack may start earlier).
        mask &= ~gt_bits(tmin, limit);
        if (!mask) continue;
        uint32_t index = cell.node;
        const TopNode* node = &s.nodes[index];
        while (!node->is_leaf()) {
            const int axis = node->axis();
            const uint32_t low = node->first_child(), high = low + 1;
            const uint32_t near = pk.forward[axis] ? low : high;
            const uint32_t far = pk.forward[axis] ? high : low;
            const V t_split =
                (splat(node->split(), V{}) - load(pk.org[axis], V{})) * load(pk.inv[axis], V{});
            const V eps = load(pk.eps[axis], V{});
            const V near_max = t_split + eps, far_min = t_split - eps;
            const uint32_t need_near = not_lt_bits(near_max, tmin) & mask;
            const uint32_t need_far = not_gt_bits(far_min, tmax) & mask;
            if (!(need_near | need_far)) break;  // never: a lane needs one side at least
            if (need_far) {
                // The far cell: [max(far_min, tmin), tmax], as TopWalk pushes it or goes on.
                const V far_tmin = take_gt(far_min, tmin);
                if (!need_near) {
                    tmin = far_tmin;
                    index = far;
                    mask = need_far;
                    node = &s.nodes[index];
                    continue;
                }
                TopPacketCell& pushed = pk.stack[pk.size++];
                store(pushed.tmin, far_tmin);
                store(pushed.tmax, tmax);
                pushed.node = far;
                pushed.mask = need_far;
            }
            // The near cell: [tmin, min(near_max, tmax)]. (A lane needs one side at least:
            // need_near fails only past the split, where need_far holds.)
            tmax = take_lt(near_max, tmax);
            index = near;
            mask = need_near;
            node = &s.nodes[index];
        }
        if (!node->is_leaf()) continue;
        at = mask;
        return node;
    }
    return nullptr;
}

/// The lanes' segments [t0, t1] clipped to `box` widened by each lane's delta: clip_widened's
/// arithmetic (the shared part of TopPacketOps::reach and clip).
template <class V>
void clip_lanes(const TopPacket& pk, const Aabb& box, V& t0, V& t1) noexcept {
    const V delta = load(pk.delta, V{});
    for (int a = 0; a < 3; ++a) {
        const V lo = splat(box.lo[a], V{}) - delta, hi = splat(box.hi[a], V{}) + delta;
        const V org = load(pk.org[a], V{}), inv = load(pk.inv[a], V{});
        const V a0 = (lo - org) * inv;
        const V a1 = (hi - org) * inv;
        // n0 = a0 > a1 ? a1 : a0 and n1 = a0 > a1 ? a0 : a1 (clip_widened's swap).
        const V n0 = take_lt(a1, a0), n1 = take_gt(a0, a1);
        t0 = take_gt(n0, t0);
        t1 = take_lt(n1, t1);
    }
}

/// TopPacketOps::reach.
template <class V>
uint32_t reach_steps(const TopPacket& pk, const Aabb& box, const Lanes& limit,
                     uint32_t mask) noexcept {
    V t0 = load(pk.ray_tmin, V{}), t1 = load(limit, V{});
    clip_lanes(pk, box, t0, t1);
    return le_bits(t0, t1) & mask;
}

/// TopPacketOps::clip: reach_steps' arithmetic, with the clipped segments kept.
template <class V>
uint32_t clip_steps(const TopPacket& pk, const Aabb& box, Lanes& tmin, Lanes& tmax,
                    uint32_t mask) noexcept {
    V t0 = load(tmin, V{}), t1 = load(tmax, V{});
    clip_lanes(pk, box, t0, t1);
    store(tmin, t0);
    store(tmax, t1);
    return le_bits(t0, t1) & mask;
}

/// Whether the rays in the lanes (ray_lanes' fields, lanes from `count` on repeating lane 0) are
/// all valid and of one octant (true only where each ray's octant_or_invalid is one octant, the
/// same in every lane). Valid: every origin and direction component finite (their sum times 0
/// is 0 only then, though a sum that overflows is taken as invalid too: the caller then checks
/// ray by ray), the direction not zero, tmin <= tmax. One octant: each direction component's
/// sign bits alike in all lanes.
inline bool one_valid_octant(const Halves f[8]) noexcept {
    const F4 zero{};
    uint32_t ok = 0, sign[3];
    for (int h = 0; h < 2; ++h) {
        const F4 sum = f[0].h[h] + f[1].h[h] + f[2].h[h] + f[4].h[h] + f[5].h[h] + f[6].h[h];
        const I4 valid = (sum * zero == zero) & (f[3].h[h] <= f[7].h[h]) &
                         ((f[4].h[h] != zero) | (f[5].h[h] != zero) | (f[6].h[h] != zero));
        ok |= static_cast<uint32_t>(_mm_movemask_ps(reinterpret_cast<__m128>(valid))) << 4 * h;
    }
    for (int a = 0; a < 3; ++a)
        sign[a] = bits(reinterpret_cast<I4>(f[4 + a].h[0]), reinterpret_cast<I4>(f[4 + a].h[1]));
    const auto alike = [](uint32_t m) { return m == 0 || m == 0xffu; };
    return ok == 0xffu && alike(sign[0]) && alike(sign[1]) && alike(sign[2]);
}

/// TopPacketOps::start (Checked: TopPacketOps::start_patch).
template <class V, bool Checked = false>
uint32_t start_steps(TopPacket& pk, const SceneData& s, const Ray* rays, uint32_t first,
                     const uint16_t* order, int count, TopPacketCell* storage,
                     Lanes& limit) noexcept {
    Halves f[8];
    const Ray* block = rays + first;
    ray_lanes(block, order, count, f);
    if constexpr (Checked)
        if (!one_valid_octant(f)) return kNotOnePacket;
    pk.stack = storage;
    pk.size = 0;
    pk.ended = 0;
    for (int l = 0; l < count; ++l) pk.ray[l] = first + order[l];
    const V delta = from_halves(margin_lanes(s, f[0], f[1], f[2]), V{});
    store(pk.delta, delta);
    const V zero = splat(0.0f, V{});
    uint32_t flat = 0;  // lanes with a zero direction component (|d| <= 0: no NaN in valid rays)
    for (int a = 0; a < 3; ++a) {
        const V dir = from_halves(f[4 + a], V{});
        const V inv = splat(1.0f, V{}) / dir;
        flat |= le_bits(abs(dir), zero);
        store(pk.org[a], from_halves(f[a], V{}));
        store(pk.dir[a], dir);
        store(pk.inv[a], inv);
        store(pk.eps[a], delta * abs(inv));  // make_top_ray's eps where no component is zero
        // The octant's sign (the same in every lane; lane 0's may be zero, but not its sign bit).
        pk.forward[a] = !__builtin_signbit((&block[order[0]].dx)[a]);
    }
    flat &= (1u << count) - 1u;
    pk.lanes = (1u << count) - 1u - flat;
    const V tmin = from_halves(f[3], V{}), tmax = from_halves(f[7], V{});
    store(pk.ray_tmin, tmin);
    store(limit, tmax);
    if (s.refs.empty()) return flat;
    V t0 = tmin, t1 = tmax;
    clip_lanes(pk, s.bounds, t0, t1);
    const uint32_t mask = le_bits(t0, t1) & pk.lanes;
    if (!mask) return flat;
    TopPacketCell& root = pk.stack[pk.size++];
    store(root.tmin, t0);
    store(root.tmax, t1);
    root.node = 0;
    root.mask = mask;
    return flat;
}

/// TopPacketOps::object_rays: to_object's arithmetic on four lanes at a time (per object axis i,
/// float(inv[i][0] * x + inv[i][1] * y + inv[i][2] * z) in double, left to right, with
/// x = double(org) - trans for the origin and x = double(dir) for the direction), then each lane's
/// ray written whole (4 x 4 transposes back).
void object_rays_steps(const TopPacket& pk, const InstanceData& in, const Lanes& tmax,
                       Ray* out) noexcept {
    using D4 = double __attribute__((vector_size(32)));
    for (int h = 0; h < 2; ++h) {
        D4 o[3], d[3];
        for (int a = 0; a < 3; ++a) {
            o[a] = __builtin_convertvector(pk.org[a].h[h], D4) - in.trans[a];
            d[a] = __builtin_convertvector(pk.dir[a].h[h], D4);
        }
        __m128 lo[4], hi[4];
        for (int i = 0; i < 3; ++i) {
            const double* m = &in.inv[3 * i];
            lo[i] = reinterpret_cast<__m128>(
                __builtin_convertvector(m[0] * o[0] + m[1] * o[1] + m[2] * o[2], F4));
            hi[i] = reinterpret_cast<__m128>(
                __builtin_convertvector(m[0] * d[0] + m[1] * d[1] + m[2] * d[2], F4));
        }
        lo[3] = reinterpret_cast<__m128>(pk.ray_tmin.h[h]);
        hi[3] = reinterpret_cast<__m128>(tmax.h[h]);
        _MM_TRANSPOSE4_PS(lo[0], lo[1], lo[2], lo[3]);
        _MM_TRANSPOSE4_PS(hi[0], hi[1], hi[2], hi[3]);
        for (int k = 0; k < 4; ++k) {
            _mm_storeu_ps(&out[4 * h + k].ox, lo[k]);
            _mm_storeu_ps(&out[4 * h + k].dx, hi[k]);
        }
    }
}

}  // namespace
}  // namespace kdrt::detail
