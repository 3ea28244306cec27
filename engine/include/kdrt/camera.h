#pragma once
/// Cameras that turn pixel coordinates into primary rays.

#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>

#include "kdrt/camera_spec.h"
#include "kdrt/types.h"

namespace kdrt {

/// Thrown for a camera that cannot form an image (bad fov, zero size, eye == look_at, up
/// parallel to the view direction); what() names the field.
class CameraError : public std::invalid_argument {
public:
    using std::invalid_argument::invalid_argument;
};

/// A camera prepared for an image of width x height pixels: an orthonormal basis and the
/// image-plane extents. Pixel (x, y) has y = 0 at the top row.
class Camera {
public:
    /// Throws CameraError naming the bad field.
    Camera(const CameraSpec& spec, uint32_t width, uint32_t height);

    /// The ray through image position (px, py) in pixels (0..width, 0..height; pixel centres at
    /// +0.5). tmin = 0, tmax = +inf; direction normalised.
    [[nodiscard]] Ray ray(float px, float py) const noexcept {
        return ray_at(plane_x(px), plane_y(py));
    }

    /// ray() in two steps, for callers that make many rays per image row or column (the
    /// renderer's tiles): plane_x / plane_y map a pixel position to image-plane coordinates (each
    /// depends on px or py alone, so a tile computes them once per column and row) and ray_at
    /// builds the ray there. ray(px, py) is ray_at(plane_x(px), plane_y(py)), bit for bit.
    [[nodiscard]] float plane_x(float px) const noexcept {
        return (2.0f * px / static_cast<float>(width_) - 1.0f) * half_w_;
    }
    [[nodiscard]] float plane_y(float py) const noexcept {
        return (1.0f - 2.0f * py / static_cast<float>(height_)) * half_h_;
    }
    [[nodiscard]] Ray ray_at(float sx, float sy) const noexcept {
        // Image plane coordinates are in [-half_w, half_w] x [-half_h, half_h], y up.
        Vec3 origin = spec_.eye;
        Vec3 dir = forward_;
        if (spec_.projection == Projection::kOrthographic) {
            origin = spec_.eye + right_ * sx + up_ * sy;
        } else {
            const Vec3 v = forward_ + right_ * sx + up_ * sy;
            dir = v * (1.0f / std::sqrt(dot(v, v)));
        }
        return Ray{origin.x, origin.y, origin.z, 0.0f,
                   dir.x,    dir.y,    dir.z,    std::numeric_limits<float>::infinity()};
    }

    [[nodiscard]] const CameraSpec& spec() const noexcept { return spec_; }
    [[nodiscard]] uint32_t width() const noexcept { return width_; }
    [[nodiscard]] uint32_t height() const noexcept { return height_; }

private:
    CameraSpec spec_;
    uint32_t width_, height_;
    Vec3 forward_, right_, up_;
    float half_w_, half_h_;
};

/// A perspective view that frames `bounds` from the front (+z looking towards -z), slightly from
/// above and to the side, with the whole box in view at the given aspect (width / height).
[[nodiscard]] CameraSpec default_camera(const Aabb& bounds, float aspect = 1.0f);

}  // namespace kdrt
