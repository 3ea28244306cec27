#pragma once
/// Value types of the distance queries (kdrt/distance.h): the closest point on a mesh to a query
/// point, and which side of the surface the point is on. No behaviour; the standard library only.

#include <cstdint>
#include <limits>

#include "kdrt/types.h"

namespace kdrt {

/// The feature of a triangle a closest point lies on: its interior, one of its edges (between
/// corners 0-1, 1-2, 2-0) or one of its corners. The values are the wire values (FORMATS.md).
enum class Feature : uint8_t {
    kFace = 0,
    kEdge01 = 1,
    kEdge12 = 2,
    kEdge20 = 3,
    kVertex0 = 4,
    kVertex1 = 5,
    kVertex2 = 6,
    kNone = 7,  ///< nothing found (no triangle within the maximum distance, or an invalid point)
};

/// Which side of the surface a point is on. kUnknown when the mesh is not closed and
/// consistently oriented (SurfaceIndex::closed), when nothing was found, or when the sign was not
/// asked for. The values are the wire values.
enum class Side : uint8_t {
    kOutside = 0,  ///< on the side the triangles' right-hand normals point to, or on the surface
    kInside = 1,
    kUnknown = 2,
};

/// The closest point on a mesh to a query point p. Nothing found: distance = +inf,
/// prim = kNoHit, u = v = 0, point = (NaN, NaN, NaN), feature = kNone, side = kUnknown.
struct ClosestPoint {
    float distance = std::numeric_limits<float>::infinity();  ///< |p - point|, rounded once
    uint32_t prim = kNoHit;  ///< the triangle, in the mesh's input order
    /// Barycentric weights of the triangle's v1 and v2, as in Hit: point = (1-u-v) v0 + u v1 + v v2
    /// (computed in double, then each rounded to float).
    float u = 0.0f;
    float v = 0.0f;
    Vec3 point{std::numeric_limits<float>::quiet_NaN(), std::numeric_limits<float>::quiet_NaN(),
               std::numeric_limits<float>::quiet_NaN()};
    Feature feature = Feature::kNone;
    Side side = Side::kUnknown;

    [[nodiscard]] bool found() const noexcept { return prim != kNoHit; }
    /// -distance inside, +distance outside; NaN when the side is unknown.
    [[nodiscard]] float signed_distance() const noexcept {
        return side == Side::kInside    ? -distance
               : side == Side::kOutside ? distance
                                        : std::numeric_limits<float>::quiet_NaN();
    }
};

}  // namespace kdrt
