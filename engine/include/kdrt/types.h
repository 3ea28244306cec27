#pragma once
/// Plain value types shared by the engine, proto and everything above them.
/// No behaviour beyond trivial helpers; no dependencies but the standard library.

#include <cstdint>
#include <limits>

namespace kdrt {

/// A ray as a line segment: points o + t*d for tmin <= t <= tmax.
/// The member order is the KDRR wire record (proto/FORMATS.md): 8 little-endian f32.
/// The direction need not be normalised; t is measured in units of |d|.
/// Valid rays have finite origin and direction, a non-zero direction, tmin and tmax not NaN
/// (either may be infinite: tmax = +inf is the usual open ray) and tmin <= tmax. Any other ray
/// never hits anything.
struct Ray {
    float ox, oy, oz, tmin;
    float dx, dy, dz, tmax;
};
static_assert(sizeof(Ray) == 32);

/// Sentinel triangle id of a miss.
inline constexpr uint32_t kNoHit = 0xFFFFFFFFu;

/// A closest-hit answer. The member order is the KDRH wire record.
/// Hit point P = (1-u-v)*v0 + u*v1 + v*v2 of triangle `prim` (input order). A miss is
/// t = +inf, prim = kNoHit, u = v = 0.
struct Hit {
    float t = std::numeric_limits<float>::infinity();
    uint32_t prim = kNoHit;
    float u = 0.0f;
    float v = 0.0f;

    [[nodiscard]] bool is_hit() const noexcept { return prim != kNoHit; }
};
static_assert(sizeof(Hit) == 16);

struct Vec3 {
    float x = 0, y = 0, z = 0;

    constexpr float operator[](int i) const noexcept { return i == 0 ? x : (i == 1 ? y : z); }
    constexpr float& operator[](int i) noexcept { return i == 0 ? x : (i == 1 ? y : z); }
    friend constexpr Vec3 operator+(Vec3 a, Vec3 b) noexcept {
        return {a.x + b.x, a.y + b.y, a.z + b.z};
    }
    friend constexpr Vec3 operator-(Vec3 a, Vec3 b) noexcept {
        return {a.x - b.x, a.y - b.y, a.z - b.z};
    }
    friend constexpr Vec3 operator*(Vec3 a, float s) noexcept {
        return {a.x * s, a.y * s, a.z * s};
    }
    friend constexpr Vec3 operator*(float s, Vec3 a) noexcept { return a * s; }
    friend constexpr bool operator==(Vec3, Vec3) = default;
};

constexpr float dot(Vec3 a, Vec3 b) noexcept { return a.x * b.x + a.y * b.y + a.z * b.z; }
constexpr Vec3 cross(Vec3 a, Vec3 b) noexcept {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

/// Axis-aligned box. The default box is empty (lo = +inf, hi = -inf).
struct Aabb {
    Vec3 lo{std::numeric_limits<float>::infinity(), std::numeric_limits<float>::infinity(),
            std::numeric_limits<float>::infinity()};
    Vec3 hi{-std::numeric_limits<float>::infinity(), -std::numeric_limits<float>::infinity(),
            -std::numeric_limits<float>::infinity()};

    [[nodiscard]] constexpr bool empty() const noexcept {
        return !(lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z);
    }
    constexpr void extend(Vec3 p) noexcept {
        for (int a = 0; a < 3; ++a) {
            lo[a] = p[a] < lo[a] ? p[a] : lo[a];
            hi[a] = p[a] > hi[a] ? p[a] : hi[a];
        }
    }
    [[nodiscard]] constexpr Vec3 extent() const noexcept { return hi - lo; }
    friend constexpr bool operator==(const Aabb&, const Aabb&) = default;
};

}  // namespace kdrt
