#include "kdrt/camera.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <string>

#include "format.h"
#include "geometry.h"

namespace kdrt {
namespace {

using detail::format_vec_fixed;
using detail::is_finite;
using detail::scene_box;

// The basis and extents are computed once per camera in double and rounded to float: the float
// results then do not depend on the order of a handful of operations, and the only libm call (tan)
// is made on a double whose rounding to float is stable across libms in practice.
struct DVec3 {
    double x, y, z;
};

DVec3 to_double(Vec3 v) noexcept { return {v.x, v.y, v.z}; }
Vec3 to_float(DVec3 v) noexcept {
    return {static_cast<float>(v.x), static_cast<float>(v.y), static_cast<float>(v.z)};
}
DVec3 sub(DVec3 a, DVec3 b) noexcept { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
DVec3 add(DVec3 a, DVec3 b) noexcept { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
DVec3 scale(DVec3 a, double s) noexcept { return {a.x * s, a.y * s, a.z * s}; }
double dot(DVec3 a, DVec3 b) noexcept { return a.x * b.x + a.y * b.y + a.z * b.z; }
DVec3 cross(DVec3 a, DVec3 b) noexcept {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
double length(DVec3 a) noexcept { return std::sqrt(dot(a, a)); }

void require_finite(Vec3 v, const char* field) {
    if (!is_finite(v)) {
        throw CameraError(std::string("camera ") + field + " " + format_vec_fixed(v) +
                          " has a NaN or infinite component");
    }
}

// tan(20 deg): half of the default vertical field of view. A constant, so default_camera makes no
// libm call and frames a box identically everywhere.
constexpr float kDefaultFovDeg = 40.0f;
constexpr double kTanHalfDefaultFov = 0.36397023426620234;
// The direction from the box centre to the eye: in front (+z), a little above and to the right.
constexpr DVec3 kDefaultViewDir{0.35, 0.25, 1.0};
// Extra room around the bounding sphere so the silhouette does not touch the image border.
constexpr double kFrameMargin = 1.05;

}  // namespace

Camera::Camera(const CameraSpec& spec, uint32_t width, uint32_t height)
    : spec_(spec), width_(width), height_(height) {
    if (width == 0) throw CameraError("camera width must be at least 1 pixel (got 0)");
    if (height == 0) throw CameraError("camera height must be at least 1 pixel (got 0)");
    require_finite(spec.eye, "eye");
    require_finite(spec.look_at, "look_at");
    require_finite(spec.up, "up");

    double half_h = 0.0;
    switch (spec.projection) {
        case Projection::kPerspective:
            // Written as a negated range test so NaN fails too.
            if (!(spec.fov_deg > 0.0f && spec.fov_deg < 180.0f)) {
                throw CameraError("camera fov_deg " + std::to_string(spec.fov_deg) +
                                  " is outside the open range (0, 180) degrees");
            }
            half_h = std::tan(static_cast<double>(spec.fov_deg) * (std::numbers::pi / 360.0));
            break;
        case Projection::kOrthographic:
            if (!(spec.ortho_height > 0.0f) || !std::isfinite(spec.ortho_height)) {
                throw CameraError("camera ortho_height " + std::to_string(spec.ortho_height) +
                                  " must be a finite value > 0");
            }
            half_h = 0.5 * static_cast<double>(spec.ortho_height);
            break;
        default:
            throw CameraError("camera projection " +
                              std::to_string(static_cast<uint32_t>(spec.projection)) +
                              " is neither perspective (0) nor orthographic (1)");
    }

    const DVec3 view = sub(to_double(spec.look_at), to_double(spec.eye));
    const double view_len = length(view);
    if (view_len == 0.0) {
        throw CameraError("camera eye and look_at are the same point " +
                          format_vec_fixed(spec.eye) + "; the view direction is undefined");
    }
    const DVec3 up = to_double(spec.up);
    const double up_len = length(up);
    if (up_len == 0.0) throw CameraError("camera up is the zero vector");
    const DVec3 forward = scale(view, 1.0 / view_len);
    const DVec3 side = cross(forward, scale(up, 1.0 / up_len));
    const double side_len = length(side);
    // sin of the angle between up and the view direction; below ~1e-6 rad the basis is noise.
    if (side_len < 1e-6) {
        throw CameraError("camera up " + format_vec_fixed(spec.up) +
                          " is parallel to the view direction (look_at - eye)");
    }
    const DVec3 right = scale(side, 1.0 / side_len);
    const DVec3 true_up = cross(right, forward);  // unit length: right and forward are orthonormal

    forward_ = to_float(forward);
    right_ = to_float(right);
    up_ = to_float(true_up);
    half_h_ = static_cast<float>(half_h);
    half_w_ = static_cast<float>(half_h * static_cast<double>(width) / static_cast<double>(height));
}

CameraSpec default_camera(const Aabb& bounds, float aspect) {
    if (!(aspect > 0.0f) || !std::isfinite(aspect)) {
        throw CameraError("camera aspect " + std::to_string(aspect) +
                          " must be a finite value > 0");
    }
    // An empty or non-finite box (an empty mesh) is framed as the unit cube around the origin.
    const Aabb box = scene_box(bounds);
    const DVec3 lo = to_double(box.lo);
    const DVec3 hi = to_double(box.hi);
    const DVec3 centre = scale(add(lo, hi), 0.5);
    double radius = 0.5 * length(sub(hi, lo));
    // A point or a tiny box far from the origin: keep the eye a float-resolvable distance away.
    const double magnitude =
        std::max({std::fabs(centre.x), std::fabs(centre.y), std::fabs(centre.z)});
    radius = std::max(radius, 1e-4 * magnitude);
    if (radius == 0.0) radius = 0.5;  // a single point at the origin

    // The camera basis for the fixed view direction; up = +y is never parallel to it.
    const DVec3 to_eye = scale(kDefaultViewDir, 1.0 / length(kDefaultViewDir));
    const DVec3 forward = scale(to_eye, -1.0);
    const DVec3 side = cross(forward, DVec3{0.0, 1.0, 0.0});
    const DVec3 right = scale(side, 1.0 / length(side));
    const DVec3 up = cross(right, forward);

    // The closest eye distance D at which every box corner projects inside the image, shrunk by
    // the margin: a corner at offset v from the centre has depth D + v.forward and must satisfy
    // |v.right| <= tan_w * depth and |v.up| <= tan_h * depth. Tighter than the bounding sphere,
    // so the box fills the image. The eye also stays outside the bounding sphere (and the box).
    const double tan_h = kTanHalfDefaultFov / kFrameMargin;
    const double tan_w = tan_h * aspect;
    double distance = kFrameMargin * radius;
    double half_x = 0.0, half_y = 0.0;  // largest |v.right|, |v.up|: the orthographic extents
    for (int corner = 0; corner < 8; ++corner) {
        const DVec3 v = sub(DVec3{(corner & 1) ? hi.x : lo.x, (corner & 2) ? hi.y : lo.y,
                                  (corner & 4) ? hi.z : lo.z},
                            centre);
        const double x = std::fabs(dot(v, right));
        const double y = std::fabs(dot(v, up));
        const double depth_offset = dot(v, forward);
        distance = std::max({distance, x / tan_w - depth_offset, y / tan_h - depth_offset});
        half_x = std::max(half_x, x);
        half_y = std::max(half_y, y);
    }

    CameraSpec spec;
    spec.eye = to_float(add(centre, scale(to_eye, distance)));
    if (!is_finite(spec.eye)) {
        throw CameraError(
            "camera bounds are too large to frame in single precision: eye would be " +
            format_vec_fixed(spec.eye));
    }
    spec.look_at = to_float(centre);
    spec.up = {0.0f, 1.0f, 0.0f};
    spec.fov_deg = kDefaultFovDeg;
    // The same box fits an orthographic view of this height at this aspect.
    const double ortho_half = std::max({half_y, half_x / aspect, 1e-3 * radius});
    spec.ortho_height = static_cast<float>(2.0 * kFrameMargin * ortho_half);
    spec.projection = Projection::kPerspective;
    return spec;
}

}  // namespace kdrt
