#pragma once
/// What decides a rendered image: the shading modes, the light, the pixel region, the limits and
/// RenderSettings. Value types only (no function here needs kdrt_engine): proto and clients
/// describe renders with them; kdrt/render.h renders them.

#include <cstdint>
#include <optional>
#include <string_view>

#include "kdrt/camera_spec.h"
#include "kdrt/types.h"

namespace kdrt {

/// What a pixel shows. Every mode but kAo and kDiffuse traces primary rays only.
enum class Shading : uint32_t {
    kNormals = 0,   ///< unit geometric normal n (turned to face the camera) as 0.5 * n + 0.5
    kEyelight = 1,  ///< |N.V|: cosine between the geometric normal and the camera ray, grey
    kDepth = 2,     ///< distance t from the camera along the (normalised) camera ray, grey
    kPrimId = 3,   ///< a fixed false colour per triangle id (a hash of the id, the same everywhere)
    kAo = 4,       ///< ambient occlusion: share of ao_samples cosine-weighted rays that escape
    kDiffuse = 5,  ///< Lambertian surfaces lit by `light` with hard shadows, plus `bounces`
    kGeomId = 6,   ///< a fixed false colour per geometry id (a scene's instance; 0 for a mesh)
};

/// "normals", "eyelight", "depth", "primid", "ao", "diffuse", "geomid" (exact, lower case) -> mode.
[[nodiscard]] constexpr std::optional<Shading> parse_shading(std::string_view name) noexcept {
    if (name == "normals") return Shading::kNormals;
    if (name == "eyelight") return Shading::kEyelight;
    if (name == "depth") return Shading::kDepth;
    if (name == "primid") return Shading::kPrimId;
    if (name == "ao") return Shading::kAo;
    if (name == "diffuse") return Shading::kDiffuse;
    if (name == "geomid") return Shading::kGeomId;
    return std::nullopt;
}

/// The name parse_shading accepts; "unknown" for a value outside the enum.
[[nodiscard]] constexpr std::string_view shading_name(Shading shading) noexcept {
    switch (shading) {
        case Shading::kNormals:
            return "normals";
        case Shading::kEyelight:
            return "eyelight";
        case Shading::kDepth:
            return "depth";
        case Shading::kPrimId:
            return "primid";
        case Shading::kAo:
            return "ao";
        case Shading::kDiffuse:
            return "diffuse";
        case Shading::kGeomId:
            return "geomid";
    }
    return "unknown";
}

enum class LightKind : uint32_t {
    kDirectional = 0,  ///< parallel light from `direction` (the sun)
    kPoint = 1,        ///< light from `position`, falling off with the squared distance
};

/// The light of kDiffuse. Units: a white (albedo 1) surface facing a directional light reflects
/// radiance `intensity`; a point light gives intensity / d^2 at distance d. Occluders anywhere
/// between the surface and the light cast hard shadows.
struct Light {
    LightKind kind = LightKind::kDirectional;
    /// kDirectional: the direction from the scene towards the light (any length > 0). The default
    /// comes from above, in front of and to the right of default_camera's view.
    Vec3 direction{0.4f, 1.0f, 0.7f};
    /// kPoint: the light's position in world space.
    Vec3 position{0.0f, 0.0f, 0.0f};
    /// Finite, >= 0.
    float intensity = 1.0f;
};

/// A rectangle of pixels of the full frame: columns x .. x + width - 1, rows y .. y + height - 1
/// (row 0 at the top).
struct PixelRegion {
    uint32_t x = 0;
    uint32_t y = 0;
    uint32_t width = 0;
    uint32_t height = 0;
    friend constexpr bool operator==(const PixelRegion&, const PixelRegion&) = default;
};

/// Largest frame width or height.
inline constexpr uint32_t kMaxImageSize = 16384;
/// Largest samples per pixel.
inline constexpr uint32_t kMaxSamplesPerPixel = 65536;
/// Largest ao_samples.
inline constexpr uint32_t kMaxAoSamples = 4096;
/// Largest number of indirect bounces.
inline constexpr uint32_t kMaxBounces = 64;

/// Everything that decides an image. All fields are validated by validate_render_settings (and
/// by render); see there for the ranges.
struct RenderSettings {
    /// The view; nullopt frames the whole scene: default_camera(tree.bounds, width / height).
    std::optional<CameraSpec> camera;
    /// Full frame size in pixels, 1 .. kMaxImageSize each. The camera's aspect is width / height.
    uint32_t width = 512;
    uint32_t height = 512;
    /// The part of the frame to render (the Image has the region's size); nullopt = whole frame.
    /// Must lie inside the frame. Regions of one frame stitch bit-exactly into the full render.
    std::optional<PixelRegion> region;
    /// Samples per pixel, 1 .. kMaxSamplesPerPixel. One sample goes through the pixel centre;
    /// more are stratified: a ceil(sqrt(spp)) x ceil(spp / that) grid of cells, each sample in its
    /// own cell (picked by a per-pixel random permutation when spp does not fill the grid),
    /// jittered inside it. The pixel is the plain average of its samples.
    uint32_t spp = 1;
    Shading shading = Shading::kEyelight;
    /// Seed of every random number (jitter, AO and bounce directions, Russian roulette).
    uint64_t seed = 1;
    /// kAo: occlusion rays per sample, 1 .. kMaxAoSamples.
    uint32_t ao_samples = 16;
    /// kAo: occlusion ray length as a share of the scene's bounding-box diagonal, finite, > 0.
    float ao_distance = 0.25f;
    /// kDiffuse: the light.
    Light light;
    /// kDiffuse: surface reflectance (grey), in [0, 1].
    float albedo = 0.8f;
    /// kDiffuse: indirect bounces after the first hit, 0 .. kMaxBounces (0 = direct light only).
    /// Paths that already bounced twice continue with probability min(throughput, 0.95)
    /// (Russian roulette, re-weighted so the estimate stays unbiased).
    uint32_t bounces = 0;
    /// kDiffuse: radiance of the sky that bounce rays escaping the scene see (finite, >= 0).
    /// Camera rays that miss show `background` instead.
    float sky = 0.0f;
    /// Colour of a camera ray that misses the scene, every mode (finite components).
    Vec3 background{0.0f, 0.0f, 0.0f};
    /// Add a fourth channel: the share of a pixel's camera rays that hit the scene (coverage).
    /// With the default black background the colour is then premultiplied by alpha.
    bool alpha = false;
    /// Tile edge in pixels: 8 or 16. Tiles are the unit of scheduling, cancellation and tracing
    /// (one block of rays per tile and sample); the image does not depend on it.
    uint32_t tile_size = 16;
};

}  // namespace kdrt
