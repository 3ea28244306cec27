#pragma once
/// Value types of the sensor scans (kdrt/scan.h): a pinhole depth camera and a spinning lidar whose
/// rays are made on the server. No behaviour; the standard library only.
///
/// Frames. A pose is a 4x4 rigid transform from the sensor's frame to the world, row-major
/// (m[4 * row + col]), acting on column vectors: world = R * local + t, R = the upper-left 3x3,
/// t = (m[3], m[7], m[11]), last row 0 0 0 1. It must be rigid: every entry finite, the last row
/// exactly 0 0 0 1, and R a rotation within kPoseTolerance (every entry of R^T R - I and det R - 1
/// within +-kPoseTolerance). The pose is used as given (not re-orthonormalised).
///
/// Pinhole camera frame (OpenCV): +x right, +y down, +z forward (the optical axis). Pixel (i, j)
/// is column i (0 = left), row j (0 = top); its ray passes through the pixel centre, camera-frame
/// direction ((i + 0.5 - cx) / fx, (j + 0.5 - cy) / fy, 1).
///
/// Lidar sensor frame: +x forward, +y left, +z up (the usual vehicle frame). Azimuth a and
/// elevation e give the direction (cos e cos a, cos e sin a, sin e): azimuth 0 is +x and azimuth
/// grows counter-clockwise seen from above (+z), from +x towards +y; elevation is positive up.

#include <array>
#include <cstdint>
#include <limits>
#include <vector>

#include "kdrt/types.h"

namespace kdrt {

/// How far a pose's rotation may be from orthonormal (see the file comment).
inline constexpr double kPoseTolerance = 1e-5;

/// A 4x4 rigid sensor-to-world transform, row-major. Default: the identity.
struct Pose {
    std::array<double, 16> m{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
};

/// What a depth image holds per pixel.
enum class DepthKind : uint32_t {
    kDepth = 0,  ///< z of the hit in the camera frame (distance along the optical axis)
    kRange = 1,  ///< Euclidean distance from the camera centre along the ray
};

/// Pinhole intrinsics in pixels: focal lengths fx, fy and principal point (cx, cy); all finite,
/// fx, fy > 0. Image of width x height pixels, each >= 1.
struct PinholeIntrinsics {
    double fx = 0, fy = 0, cx = 0, cy = 0;
    uint32_t width = 0, height = 0;
};

/// A depth camera scan.
struct PinholeSpec {
    PinholeIntrinsics intrinsics;
    Pose pose;  ///< camera-to-world
    DepthKind kind = DepthKind::kDepth;
    bool normals = false;  ///< also answer each hit's geometric normal
    /// Only hits with min_range <= range <= max_range count (range along the ray, world units):
    /// 0 <= min_range < max_range, min_range finite, max_range finite or +inf.
    float min_range = 0.0f;
    float max_range = std::numeric_limits<float>::infinity();
};

/// A depth image. Pixel (i, j) is entry j * width + i. A pixel whose ray hits nothing within the
/// range: depth +inf, prim kNoHit (0xFFFFFFFF), normal (0, 0, 0).
struct DepthImage {
    uint32_t width = 0, height = 0;
    DepthKind kind = DepthKind::kDepth;
    std::vector<float> depth;    ///< width * height, depth or range by `kind`
    std::vector<uint32_t> prim;  ///< width * height, the triangle hit (mesh input order)
    std::vector<Vec3> normals;   ///< width * height when asked for, else empty; see scan.h
};

/// A spinning lidar scan: channels (beams fired together, one elevation each) times azimuth_steps
/// firings evenly spaced over 360 degrees (step k at azimuth 360 * k / azimuth_steps degrees).
struct LidarSpec {
    /// Per channel, in degrees, each finite and in [-90, 90]; at least 1. Channel c is entry c.
    std::vector<double> elevation_deg;
    uint32_t azimuth_steps = 0;  ///< >= 1
    float min_range = 0.0f;      ///< as PinholeSpec
    float max_range = std::numeric_limits<float>::infinity();
    uint32_t returns = 1;  ///< at most this many hits per beam, nearest first: 1 .. kMaxHitsPerRay
    Pose pose;             ///< sensor-to-world
};

/// One lidar return. The KDRL wire record (proto/FORMATS.md): 4 little-endian f32, 4 u32.
struct LidarPoint {
    float x = 0, y = 0, z = 0;  ///< world-space hit point (on the triangle, see scan.h)
    float range = 0;            ///< distance from the sensor origin along the beam
    uint32_t channel = 0;
    uint32_t azimuth_index = 0;
    uint32_t return_index = 0;  ///< 0 = nearest hit of the beam
    uint32_t prim = 0;          ///< the triangle hit (mesh input order)
};
static_assert(sizeof(LidarPoint) == 32);

/// A lidar scan's returns in beam order: azimuth-major (all channels of azimuth step 0, channel 0
/// first, then step 1, ...), and within a beam by return index. Beams without a hit in range
/// contribute no point.
struct PointCloud {
    uint32_t channels = 0, azimuth_steps = 0, returns = 0;
    std::vector<LidarPoint> points;
};

}  // namespace kdrt
