#pragma once
// Internal: per-ray set-up and the watertight ray/triangle test shared by every traversal path.
// Everything here is header-only so the scalar kernel and the per-ISA packet kernels compute
// bit-identical results (the build uses -ffp-contract=off: no FMA contraction).
//
// The functions are `static inline` and use compiler builtins rather than <cmath>: the per-ISA
// translation units include this header too, and a function with external linkage emitted there
// (compiled for AVX-512, say) could be the copy the linker keeps for the whole program. With
// internal linkage every translation unit keeps its own copy, compiled for its own target.

#include <cstdint>
#include <limits>

#include "kdrt/kdtree.h"
#include "kdrt/types.h"

namespace kdrt::detail {

/// True for a ray the engine traces (see Ray's contract); everything else is a miss.
static inline bool ray_is_valid(const Ray& r) noexcept {
    const bool finite = __builtin_isfinite(r.ox) && __builtin_isfinite(r.oy) &&
                        __builtin_isfinite(r.oz) && __builtin_isfinite(r.dx) &&
                        __builtin_isfinite(r.dy) && __builtin_isfinite(r.dz);
    const bool nonzero = r.dx != 0.0f || r.dy != 0.0f || r.dz != 0.0f;
    return finite && nonzero && r.tmin <= r.tmax;  // false for a NaN tmin or tmax
}

/// Ray data prepared once per ray: reciprocal direction for traversal and the shear constants of
/// Woop, Benthin & Wald 2013 ("Watertight Ray/Triangle Intersection") for the triangle test.
struct PreparedRay {
    float org[3];
    float inv_dir[3];
    int kx, ky, kz;
    float sx, sy, sz;
};

/// The three edge functions of a triangle in the ray's frame, redone in double, where the
/// products of floats are exact: the retry every triangle test (scalar, four triangles, packet
/// lanes) makes when one of them came out exactly zero.
[[gnu::always_inline]] static inline void exact_edges(float ax, float ay, float bx, float by,
                                                      float cx, float cy, float& u, float& v,
                                                      float& w) noexcept {
    u = static_cast<float>(static_cast<double>(cx) * by - static_cast<double>(cy) * bx);
    v = static_cast<float>(static_cast<double>(ax) * cy - static_cast<double>(ay) * cx);
    w = static_cast<float>(static_cast<double>(bx) * ay - static_cast<double>(by) * ax);
}

/// The shear constants of `p` (kx, ky, kz, sx, sy, sz) for the direction `dir`; p.inv_dir must
/// hold its reciprocal already.
static inline void prepare_shear(const float dir[3], PreparedRay& p) noexcept {
    // kz: the dimension where the direction is largest in magnitude; first such on ties.
    const float ax = __builtin_fabsf(dir[0]), ay = __builtin_fabsf(dir[1]),
                az = __builtin_fabsf(dir[2]);
    // Without branches (which way a ray points is a coin toss for the branch predictor): y wins
    // over x only when larger, z over both only when larger than the winner.
    const int y_wins = ay > ax ? 1 : 0;
    const int z_wins = az > (ay > ax ? ay : ax) ? 1 : 0;
    const int kz = (z_wins << 1) | (y_wins & (z_wins ^ 1));
    // kx, ky: the next axes after kz, cyclically ((kz + 1) % 3, (kz + 2) % 3, two bits each),
    // swapped where dir[kz] < 0 to keep the winding, so the signs of U, V, W mean the same side.
    const int next1 = (0x09 >> (2 * kz)) & 3, next2 = (0x12 >> (2 * kz)) & 3;
    const int swap = (next1 ^ next2) & -(dir[kz] < 0.0f ? 1 : 0);
    const int kx = next1 ^ swap, ky = next2 ^ swap;
    p.kx = kx;
    p.ky = ky;
    p.kz = kz;
    p.sx = dir[kx] / dir[kz];
    p.sy = dir[ky] / dir[kz];
    p.sz = p.inv_dir[kz];  // 1 / dir[kz], computed once
}

static inline PreparedRay prepare_ray(const Ray& r) noexcept {
    PreparedRay p;
    const float dir[3] = {r.dx, r.dy, r.dz};
    p.org[0] = r.ox;
    p.org[1] = r.oy;
    p.org[2] = r.oz;
    for (int a = 0; a < 3; ++a) p.inv_dir[a] = 1.0f / dir[a];  // +-inf for a zero component
    prepare_shear(dir, p);
    return p;
}

/// Watertight test of one triangle against the prepared ray `p`. On a hit at t >= tmin (t not
/// NaN), returns true and writes t and the barycentrics u (of v1) and v (of v2) into t_out, u_out,
/// v_out; otherwise returns false and writes nothing. The upper bound and the tie rule (closest t,
/// then lowest prim) are the caller's. No hit is ever reported for a degenerate triangle or a ray
/// in the triangle's plane.
static inline bool intersect_triangle(const PreparedRay& p, const TriVerts& tri, float tmin,
                                      float& t_out, float& u_out, float& v_out) noexcept {
    // Vertices relative to the origin, in the ray's permuted frame (kx, ky, kz).
    const float a_x = tri.v0[p.kx] - p.org[p.kx], a_y = tri.v0[p.ky] - p.org[p.ky],
                a_z = tri.v0[p.kz] - p.org[p.kz];
    const float b_x = tri.v1[p.kx] - p.org[p.kx], b_y = tri.v1[p.ky] - p.org[p.ky],
                b_z = tri.v1[p.kz] - p.org[p.kz];
    const float c_x = tri.v2[p.kx] - p.org[p.kx], c_y = tri.v2[p.ky] - p.org[p.ky],
                c_z = tri.v2[p.kz] - p.org[p.kz];
    // Shear so the ray runs along +z through the origin.
    const float ax = a_x - p.sx * a_z, ay = a_y - p.sy * a_z;
    const float bx = b_x - p.sx * b_z, by = b_y - p.sy * b_z;
    const float cx = c_x - p.sx * c_z, cy = c_y - p.sy * c_z;
    float u = cx * by - cy * bx;
    float v = ax * cy - ay * cx;
    float w = bx * ay - by * ax;
    // An edge function of exactly zero may be a rounding accident: redo all three in double, where
    // the products of floats are exact, so a ray on a shared edge is decided consistently.
    if (u == 0.0f || v == 0.0f || w == 0.0f) exact_edges(ax, ay, bx, by, cx, cy, u, v, w);
    // Decided without a branch until the end: whether a ray misses a triangle is as good as a
    // coin toss for the branch predictor, while a leaf's tests mostly end in "no hit", which it
    // predicts well. The division is made either way (its value only counts on a hit).
    const bool outside =
        ((u < 0.0f) | (v < 0.0f) | (w < 0.0f)) & ((u > 0.0f) | (v > 0.0f) | (w > 0.0f));
    const float det = u + v + w;
    const float az = p.sz * a_z;
    const float bz = p.sz * b_z;
    const float cz = p.sz * c_z;
    const float t_scaled = u * az + v * bz + w * cz;
    const float t = t_scaled / det;
    // t >= tmin also rejects NaN.
    if (outside | (det == 0.0f) | !(t >= tmin)) return false;
    t_out = t;
    u_out = v / det;
    v_out = w / det;
    return true;
}

/// Clips [tmin, tmax] of a ray to a box, widened by the traversal tolerance `eps` (traversal_eps)
/// as every cell's interval is: the slab distances of a ray from far away round by a few ulps of
/// its origin, far more than the box's padding, and an unwidened clip would cut off hits near the
/// box's corners and edges that the triangle test reports. False when the ray misses the box.
/// Zero direction components are handled without NaN: the slab either contains the origin (no
/// constraint; the triangle test is exact in that axis) or not (miss).
static inline bool clip_to_box(const PreparedRay& p, const Aabb& box, const float eps[3],
                               float& tmin, float& tmax) noexcept {
    for (int a = 0; a < 3; ++a) {
        if (__builtin_isinf(p.inv_dir[a])) {
            if (p.org[a] < box.lo[a] || p.org[a] > box.hi[a]) return false;
            continue;
        }
        float t0 = (box.lo[a] - p.org[a]) * p.inv_dir[a];
        float t1 = (box.hi[a] - p.org[a]) * p.inv_dir[a];
        if (t0 > t1) {
            const float tmp = t0;
            t0 = t1;
            t1 = tmp;
        }
        t0 -= eps[a];
        t1 += eps[a];
        tmin = t0 > tmin ? t0 : tmin;
        tmax = t1 < tmax ? t1 : tmax;
    }
    return tmin <= tmax;
}

/// Largest coordinate magnitude of a box.
static inline float bounds_magnitude(const Aabb& bounds) noexcept {
    float m = 0.0f;
    for (int a = 0; a < 3; ++a) {
        const float lo = __builtin_fabsf(bounds.lo[a]), hi = __builtin_fabsf(bounds.hi[a]);
        m = lo > m ? lo : m;
        m = hi > m ? hi : m;
    }
    return m;
}

/// Spatial margin by which traversal widens its cells: 16 ulps of the largest coordinate magnitude
/// of the scene and the ray origin, comfortably above the rounding of the triangle test.
/// `bounds_mag`: bounds_magnitude of the scene's bounds (a batch computes it once).
static inline float interval_margin(const PreparedRay& p, float bounds_mag) noexcept {
    // Plain comparisons, not fmaxf (a libm call): the inputs are never NaN here, and the packet
    // kernels take the same maximum lane by lane.
    float m = bounds_mag;
    // NOLINTNEXTLINE(modernize-loop-convert): kernel code, kept as reviewed (no rewrites here)
    for (int a = 0; a < 3; ++a) {
        const float o = __builtin_fabsf(p.org[a]);
        m = o > m ? o : m;
    }
    return m * 0x1p-20f;
}

/// Per-axis tolerance of the cell intervals in t. The watertight test decides hits to within a
/// few ulps of the coordinates (its shear rounds), so a ray through a cell corner or along a split
/// plane may hit a triangle in a cell that its rounded plane crossings would skip. Each interval
/// is widened by the spatial margin of interval_margin, converted to t along the split axis
/// (margin / |d_axis|). Axis-parallel directions (infinite reciprocal) need none: their triangle
/// tests are exact in that axis.
static inline void traversal_eps(const PreparedRay& p, float bounds_mag, float eps[3]) noexcept {
    const float delta = interval_margin(p, bounds_mag);
    for (int a = 0; a < 3; ++a)
        eps[a] = __builtin_isinf(p.inv_dir[a]) ? 0.0f : delta * __builtin_fabsf(p.inv_dir[a]);
}
static inline void traversal_eps(const PreparedRay& p, const Aabb& bounds, float eps[3]) noexcept {
    traversal_eps(p, bounds_magnitude(bounds), eps);
}

}  // namespace kdrt::detail
