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
/// Describing a render needs only the value types of kdrt/render_settings.h and kdrt/image.h
/// (proto and clients use those without linking kdrt_engine); this header adds what kdrt_engine
/// defines: validate_render_settings(), render() and its hooks and statistics.

#include <atomic>
#include <cstdint>
#include <functional>
#include <stdexcept>
#include <vector>

#include "kdrt/camera.h"
#include "kdrt/image.h"
#include "kdrt/kdtree.h"
#include "kdrt/render_settings.h"
#include "kdrt/types.h"

namespace kdrt {

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
/// Values: kNormals in [0, 1]; kEyelight in [0, 1]; kDepth = distance in world units; kPrimId and
/// kGeomId in [0, 1]; kAo in [0, 1]; kDiffuse in [0, inf). Camera rays that miss give `background`
/// and alpha 0. Secondary rays start on the hit triangle, pushed off the surface towards the side
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
