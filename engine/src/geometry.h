#pragma once
// Internal: small geometry helpers shared by the builders, the statistics, the camera, ray-set
// generation and the renderer. Square roots only, no libm transcendentals, so the bits are the
// same with every C library.

#include <algorithm>
#include <cmath>
#include <span>

#include "kdrt/kdtree.h"
#include "kdrt/types.h"

namespace kdrt::detail {

/// Coincident hits merge (AllHitsOptions::merge_coincident) within this fraction of the largest
/// coordinate of the ray origin and the group's first triangle, over the largest direction
/// component: multi_hit.cpp's merge, and the window scene_trace.cpp's nearest hits look through.
inline constexpr float kMergeToleranceScale = 0x1p-18f;

inline bool is_finite(Vec3 v) noexcept {
    return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z);
}

/// v scaled to unit length (NaN components for a zero or non-finite v).
inline Vec3 normalized(Vec3 v) noexcept { return v * (1.0f / std::sqrt(dot(v, v))); }

/// Half the surface area of a box, in double (the SAH's area ratios).
inline double half_area(const Aabb& b) noexcept {
    const double x = double{b.hi.x} - b.lo.x, y = double{b.hi.y} - b.lo.y,
                 z = double{b.hi.z} - b.lo.z;
    return x * y + y * z + z * x;
}

/// The box the default camera, ray sets and secondary rays work with: `bounds`, or the unit cube
/// around the origin when `bounds` is empty or not finite (an empty mesh).
inline Aabb scene_box(const Aabb& bounds) noexcept {
    if (!bounds.empty() && is_finite(bounds.lo) && is_finite(bounds.hi)) return bounds;
    return Aabb{{-0.5f, -0.5f, -0.5f}, {0.5f, 0.5f, 0.5f}};
}

/// Length of the diagonal of `box`.
inline float diagonal(const Aabb& box) noexcept {
    const Vec3 ext = box.extent();
    return std::sqrt(dot(ext, ext));
}

/// Distance a secondary ray's origin is pushed off the surface. Relative to the scene size and to
/// the magnitude of the coordinates (far from the origin a float has fewer bits below the point):
/// about 100 ulps of the largest coordinate, far below the size of any visible triangle.
inline float surface_offset(const Aabb& box) noexcept {
    float magnitude = 0.0f;
    for (int a = 0; a < 3; ++a)
        magnitude = std::max({magnitude, std::fabs(box.lo[a]), std::fabs(box.hi[a])});
    return 1e-5f * (diagonal(box) + magnitude);
}

inline Vec3 direction(const Ray& r) noexcept { return {r.dx, r.dy, r.dz}; }

/// How facing_normal scales the double cross product to unit length: n * (1 / |n|) or n / |n|.
/// They round alike but for rare ties; the renderer and the ray-set generator each keep theirs,
/// so images and ray sets stay bit-identical to the ones they always gave.
enum class NormalScaling { kReciprocal, kDivision };

/// The cross product (v1 - v0) x (v2 - v0) of `tri`'s edges into `n`, in double (sliver
/// triangles lose most of its bits in float), and its length.
inline double edge_cross(const TriVerts& tri, double n[3]) noexcept {
    const double e1[3] = {double{tri.v1[0]} - tri.v0[0], double{tri.v1[1]} - tri.v0[1],
                          double{tri.v1[2]} - tri.v0[2]};
    const double e2[3] = {double{tri.v2[0]} - tri.v0[0], double{tri.v2[1]} - tri.v0[1],
                          double{tri.v2[2]} - tri.v0[2]};
    n[0] = e1[1] * e2[2] - e1[2] * e2[1];
    n[1] = e1[2] * e2[0] - e1[0] * e2[2];
    n[2] = e1[0] * e2[1] - e1[1] * e2[0];
    return std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
}

/// Unit geometric normal of `tri` facing against `dir` (towards where the ray came from), for
/// spawning secondary rays. The cross product is taken in double: sliver triangles lose most bits
/// of it in float, and a wrong side would start secondary rays inside the surface.
template <NormalScaling kScaling>
Vec3 facing_normal(const TriVerts& tri, Vec3 dir) noexcept {
    double n[3];
    const double len = edge_cross(tri, n);
    if (!(len > 0.0) || !std::isfinite(len)) {
        // The engine never reports hits on zero-area triangles; stay well defined regardless.
        return normalized(dir) * -1.0f;
    }
    Vec3 normal;
    if constexpr (kScaling == NormalScaling::kReciprocal) {
        const double inv_len = 1.0 / len;
        normal = {static_cast<float>(n[0] * inv_len), static_cast<float>(n[1] * inv_len),
                  static_cast<float>(n[2] * inv_len)};
    } else {
        normal = {static_cast<float>(n[0] / len), static_cast<float>(n[1] / len),
                  static_cast<float>(n[2] / len)};
    }
    if (dot(normal, dir) > 0.0f) normal = normal * -1.0f;
    return normal;
}

/// A hit, prepared for spawning secondary rays.
struct Surface {
    Vec3 origin;  ///< the hit point, pushed off the surface along `normal`
    Vec3 normal;  ///< unit geometric normal on the side the ray came from
};

/// The surface of `hit` (a hit of `ray` on `tri`, the triangle hit.prim), its origin pushed off by
/// `offset`.
template <NormalScaling kScaling>
Surface surface_at(const TriVerts& tri, const Ray& ray, const Hit& hit, float offset) noexcept {
    const Vec3 v0{tri.v0[0], tri.v0[1], tri.v0[2]};
    const Vec3 v1{tri.v1[0], tri.v1[1], tri.v1[2]};
    const Vec3 v2{tri.v2[0], tri.v2[1], tri.v2[2]};
    // The barycentric point lies on the triangle to rounding; o + t*d can be off by |t*d| ulps.
    const Vec3 p = v0 * (1.0f - hit.u - hit.v) + v1 * hit.u + v2 * hit.v;
    const Vec3 normal = facing_normal<kScaling>(tri, direction(ray));
    return {p + normal * offset, normal};
}

}  // namespace kdrt::detail
