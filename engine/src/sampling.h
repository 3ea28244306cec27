#pragma once
// Internal: vector helpers and hemisphere sampling shared by ray-set generation (raygen.cpp) and
// the renderer (render.cpp). Square roots only, no libm transcendentals, so the bits are the same
// with every C library.

#include <cmath>

#include "kdrt/types.h"

namespace kdrt::detail {

inline Vec3 normalized(Vec3 v) noexcept { return v * (1.0f / std::sqrt(dot(v, v))); }

inline bool is_finite(Vec3 v) noexcept {
    return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z);
}

/// Cosine-weighted direction around the unit vector `n` (Malley's method: a uniform point in the
/// unit disk lifted to the hemisphere). `Rng` gives symmetric() uniform in [-1, 1).
template <class Rng>
Vec3 cosine_direction(Vec3 n, Rng& rng) noexcept {
    // Orthonormal basis from one unit vector without branches on near-zero components
    // (Duff et al. 2017, "Building an Orthonormal Basis, Revisited").
    const float sign = std::copysign(1.0f, n.z);
    const float a = -1.0f / (sign + n.z);
    const float b = n.x * n.y * a;
    const Vec3 t1{1.0f + sign * n.x * n.x * a, sign * b, -sign * n.x};
    const Vec3 t2{b, sign + n.y * n.y * a, -n.y};
    float x, y, r2;
    // Rejecting r2 > 1 - 1e-6 keeps cos(theta) >= 1e-3, so rounding cannot tip a grazing sample
    // below the surface; it drops a 1e-6 share of the distribution.
    do {
        x = rng.symmetric();
        y = rng.symmetric();
        r2 = x * x + y * y;
    } while (r2 > 1.0f - 1e-6f);
    const float z = std::sqrt(1.0f - r2);
    return normalized(t1 * x + t2 * y + n * z);
}

}  // namespace kdrt::detail
