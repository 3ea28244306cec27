#pragma once
// Internal: direction sampling shared by ray-set generation (raygen.cpp) and the renderer
// (render_shading.h). Square roots only, no libm transcendentals, so the bits are the same with
// every C library. `Rng` is a CounterRng (random.h) or anything with symmetric()
// uniform in [-1, 1).

#include <cmath>

#include "geometry.h"
#include "kdrt/types.h"

namespace kdrt::detail {

/// Cosine-weighted direction around the unit vector `n` (Malley's method: a uniform point in the
/// unit disk lifted to the hemisphere).
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

/// Direction uniform on the unit sphere: a uniform point in the unit ball, normalised.
template <class Rng>
Vec3 sphere_direction(Rng& rng) noexcept {
    Vec3 v;
    float len2;
    do {
        v = {rng.symmetric(), rng.symmetric(), rng.symmetric()};
        len2 = dot(v, v);
    } while (len2 > 1.0f || len2 < 1e-4f);
    return v * (1.0f / std::sqrt(len2));
}

}  // namespace kdrt::detail
