#pragma once
/// Images from the engine: camera rays per pixel, traced tile by tile as blocks of coherent rays
/// (intersect_block / occluded_block) over the calling thread's oneTBB arena, shaded into a linear
/// float buffer. Encoding the buffer as PNG/JPEG/EXR is proto's job (kdrt/proto/image_io.h).
///
/// Determinism: every random number of a pixel comes from a hash of (seed, pixel x and y in the
/// full frame, sample index, purpose), never from a shared sequence, and every pixel is computed
/// from its own rays only. So an image is bit-identical at any thread count and tile size, and the
/// regions of a frame stitch into exactly the full frame.
///
/// Only Image, the enums and the settings structs are needed to *describe* a render (proto and
/// clients use them without linking kdrt_engine); render() and validate_render_settings() live in
/// kdrt_engine.

#include <atomic>
#include <cstdint>
#include <functional>
#include <optional>
#include <stdexcept>
#include <string_view>
#include <vector>

#include "kdrt/camera.h"
#include "kdrt/kdtree.h"
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
};

/// "normals", "eyelight", "depth", "primid", "ao", "diffuse" (exact, lower case) -> mode.
[[nodiscard]] constexpr std::optional<Shading> parse_shading(std::string_view name) noexcept {
    if (name == "normals") return Shading::kNormals;
    if (name == "eyelight") return Shading::kEyelight;
    if (name == "depth") return Shading::kDepth;
    if (name == "primid") return Shading::kPrimId;
    if (name == "ao") return Shading::kAo;
    if (name == "diffuse") return Shading::kDiffuse;
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

/// A linear float image, row-major, top row first, `channels` interleaved floats per pixel:
/// 3 = RGB, 4 = RGBA. pixels.size() == width * height * channels.
struct Image {
    uint32_t width = 0;
    uint32_t height = 0;
    uint32_t channels = 0;
    std::vector<float> pixels;
};

/// Thrown for settings that cannot form an image; what() names the field and the value, e.g.
/// "render spp 0 must be in 1 .. 65536". Camera problems (fov, eye == look_at, up parallel to the
/// view) come as a RenderError carrying CameraError's message.
class RenderError : public std::invalid_argument {
public:
    using std::invalid_argument::invalid_argument;
};

/// Thrown by render() when RenderControl::cancel was seen set before the last tile started.
/// No image is returned; the work already done is dropped.
class RenderCancelled : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// Hooks for long renders (the server's async jobs).
struct RenderControl {
    /// Called between tiles with the share of tiles done, in (0, 1]: from worker threads, one call
    /// at a time, each value larger than the one before, about every 1/256 of the work, and
    /// last with exactly 1.0 (on the calling thread, after every tile is done). An exception it
    /// throws stops the render and propagates out of render().
    std::function<void(double)> progress;
    /// Checked before each tile starts; once seen true, remaining tiles are skipped and render()
    /// throws RenderCancelled. The pointee must outlive the call. nullptr: never cancelled.
    const std::atomic<bool>* cancel = nullptr;
};

/// What one render did.
struct RenderStats {
    uint64_t pixels = 0;        ///< pixels rendered (the region's)
    uint64_t tiles = 0;         ///< tiles rendered
    uint64_t primary_rays = 0;  ///< camera rays: pixels * spp
    uint64_t rays = 0;          ///< every ray traced: camera, AO, shadow and bounce rays
    double seconds = 0;         ///< wall time of render(), validation included
};

/// Throws RenderError naming the first bad field: width/height outside 1 .. kMaxImageSize, a
/// region that is empty or not inside the frame, spp, ao_samples, bounces or tile_size out of
/// range, ao_distance, albedo, sky, light intensity/direction/position or background not finite
/// or out of range, and every CameraError of an explicit camera. (A nullopt camera is checked
/// against the tree's bounds in render().)
void validate_render_settings(const RenderSettings& settings);

/// Renders `settings` of the scene in `tree` into an Image of the region's size, with
/// 3 channels (4 with settings.alpha). Uses the calling thread's oneTBB arena; the result is
/// bit-identical at any thread count. Throws RenderError for bad settings (before any work),
/// RenderCancelled when cancelled, and lets std::bad_alloc and exceptions from the progress
/// callback through. Thread-safe: `tree` is only read; concurrent renders are fine.
///
/// Values: kNormals in [0, 1]; kEyelight in [0, 1]; kDepth = distance in world units; kPrimId in
/// [0, 1]; kAo in [0, 1]; kDiffuse in [0, inf). Camera rays that miss give `background` and
/// alpha 0. Secondary rays start on the hit triangle, pushed off the surface towards the side
/// the ray came from by 1e-5 of (scene diagonal + largest coordinate magnitude).
[[nodiscard]] Image render(const KdTree& tree, const RenderSettings& settings,
                           const RenderControl& control = {}, RenderStats* stats = nullptr);

/// The camera rays render() traces for sample `sample` (0 .. spp - 1) of every pixel of the
/// region, in row-major region order: the same bits, so other tracers can be timed or checked
/// on exactly the rays of a render. Throws RenderError like render().
[[nodiscard]] std::vector<Ray> render_camera_rays(const KdTree& tree,
                                                  const RenderSettings& settings,
                                                  uint32_t sample = 0);

}  // namespace kdrt
