// validate_render_settings: the ranges of every RenderSettings field (kdrt/render.h).

#include <cmath>
#include <cstdint>
#include <string>

#include "format.h"
#include "geometry.h"
#include "kdrt/camera.h"
#include "kdrt/render.h"
#include "render_frame.h"

namespace kdrt {
namespace {

using detail::format_float;
using detail::format_vec;
using detail::is_finite;
using detail::render_fail;

void require_range(const char* field, uint64_t value, uint64_t lo, uint64_t hi) {
    if (value < lo || value > hi) {
        render_fail(std::string(field) + " " + std::to_string(value) + " must be in " +
                    std::to_string(lo) + " .. " + std::to_string(hi));
    }
}

void require_finite_nonnegative(const char* field, float value) {
    if (!(value >= 0.0f) || !std::isfinite(value)) {
        render_fail(std::string(field) + " " + format_float(value) +
                    " must be a finite value >= 0");
    }
}

}  // namespace

void validate_render_settings(const RenderSettings& s) {
    require_range("width", s.width, 1, kMaxImageSize);
    require_range("height", s.height, 1, kMaxImageSize);
    if (s.region) {
        const PixelRegion& r = *s.region;
        if (r.width == 0 || r.height == 0) {
            render_fail("region width and height must be at least 1 (got " +
                        std::to_string(r.width) + " x " + std::to_string(r.height) + ")");
        }
        // 64-bit sums: x + width cannot wrap.
        if (uint64_t{r.x} + r.width > s.width || uint64_t{r.y} + r.height > s.height) {
            render_fail("region (x " + std::to_string(r.x) + ", y " + std::to_string(r.y) +
                        ", width " + std::to_string(r.width) + ", height " +
                        std::to_string(r.height) + ") is not inside the " +
                        std::to_string(s.width) + " x " + std::to_string(s.height) + " frame");
        }
    }
    require_range("spp", s.spp, 1, kMaxSamplesPerPixel);
    if (!parse_shading(shading_name(s.shading))) {
        render_fail("shading " + std::to_string(static_cast<uint32_t>(s.shading)) +
                    " is not a known mode");
    }
    require_range("ao_samples", s.ao_samples, 1, kMaxAoSamples);
    if (!(s.ao_distance > 0.0f) || !std::isfinite(s.ao_distance)) {
        render_fail("ao_distance " + format_float(s.ao_distance) + " must be a finite value > 0");
    }
    if (!(s.albedo >= 0.0f && s.albedo <= 1.0f))
        render_fail("albedo " + format_float(s.albedo) + " must be in [0, 1]");
    require_range("bounces", s.bounces, 0, kMaxBounces);
    require_finite_nonnegative("sky", s.sky);
    if (!is_finite(s.background))
        render_fail("background " + format_vec(s.background) + " has a NaN or infinite component");
    if (s.tile_size != 8 && s.tile_size != 16) {
        render_fail("tile_size " + std::to_string(s.tile_size) + " must be 8 or 16");
    }
    const Light& light = s.light;
    require_finite_nonnegative("light.intensity", light.intensity);
    switch (light.kind) {
        case LightKind::kDirectional: {
            const Vec3 d = light.direction;
            if (!is_finite(d) || dot(d, d) == 0.0f || !std::isfinite(dot(d, d))) {
                render_fail("light.direction " + format_vec(d) +
                            " must be finite, non-zero and not too long");
            }
            break;
        }
        case LightKind::kPoint:
            if (!is_finite(light.position)) {
                render_fail("light.position " + format_vec(light.position) +
                            " has a NaN or infinite component");
            }
            break;
        default:
            render_fail("light.kind " + std::to_string(static_cast<uint32_t>(light.kind)) +
                        " is neither directional (0) nor point (1)");
    }
    if (s.camera) {
        try {
            const Camera camera(*s.camera, s.width, s.height);
        } catch (const CameraError& e) {
            throw RenderError(e.what());
        }
    }
}

}  // namespace kdrt
