#pragma once
// Internal: what the renderer fixes once per render (Frame) and per tile (TilePixels,
// TileScratch), shared by the tile loop (render.cpp) and the shading modes (render_shading.h).

#include <array>
#include <cstdint>
#include <span>
#include <string>

#include "geometry.h"
#include "kdrt/camera.h"
#include "kdrt/kdtree.h"
#include "kdrt/render.h"
#include "kdrt/scene.h"
#include "random.h"

namespace kdrt::detail {

inline constexpr uint32_t kMaxTileSize = 16;
inline constexpr uint32_t kMaxTilePixels = kMaxTileSize * kMaxTileSize;

/// Throws RenderError("render " + message).
[[noreturn]] inline void render_fail(const std::string& message) {
    throw RenderError("render " + message);
}

/// The stratification grid of `spp` samples: columns x rows cells, columns * rows >= spp.
struct SampleGrid {
    uint32_t columns = 1;
    uint32_t rows = 1;
};

struct TileScratch;

/// Everything fixed for one render.
struct Frame {
    const RenderSettings& settings;
    Camera camera;
    PixelRegion region;
    const KdTree* tree;  ///< a mesh render: the hit triangles (KdTree::triangle); else null
    const Scene* scene;  ///< a scene render: the hit triangles (world_triangle); else null
    uint32_t channels;
    uint32_t tiles_x, tiles_y;
    SampleGrid grid;
    float offset;   ///< secondary ray origin offset along the normal
    float ao_tmax;  ///< length of an AO ray
    Vec3 to_light;  ///< kDirectional: unit direction towards the light

    /// The camera ray of sample `sample` of full-frame pixel (x, y): through the pixel centre for
    /// one sample per pixel, else through the sample's jittered position in its stratum.
    [[nodiscard]] Ray camera_ray(uint32_t x, uint32_t y, uint32_t sample) const noexcept {
        float jx = 0.5f, jy = 0.5f;
        if (settings.spp > 1) {
            const uint32_t key = pixel_rng(settings.seed, x, y, 0, PixelStream::kStrata, 0).bits();
            const uint32_t cell = permute(sample, grid.columns * grid.rows, key);
            CounterRng rng = pixel_rng(settings.seed, x, y, sample, PixelStream::kJitter, 0);
            const float u1 = rng.uniform(), u2 = rng.uniform();
            const uint32_t column = cell % grid.columns, row = cell / grid.columns;
            jx = (static_cast<float>(column) + u1) / static_cast<float>(grid.columns);
            jy = (static_cast<float>(row) + u2) / static_cast<float>(grid.rows);
        }
        return camera.ray(static_cast<float>(x) + jx, static_cast<float>(y) + jy);
    }

    /// The world-space triangle of the hit in slot i of a tile's scratch.
    [[nodiscard]] TriVerts triangle(const TileScratch& s, uint32_t i) const noexcept;
};

/// Validates `s` (validate_render_settings) and fixes everything else of the render: camera,
/// region, tiles, stratification grid, ray offsets and lengths. One of tree and scene is given.
[[nodiscard]] Frame make_frame(const KdTree* tree, const Scene* scene, const RenderSettings& s);

/// A tile's pixels, in Morton order: pixel i is (x + dx[i], y + dy[i]) of the full frame.
struct TilePixels {
    uint32_t x = 0, y = 0;  ///< top-left corner in the full frame
    uint32_t count = 0;
    std::array<uint8_t, kMaxTilePixels> dx;
    std::array<uint8_t, kMaxTilePixels> dy;

    [[nodiscard]] uint32_t pixel_count() const noexcept { return count; }
    [[nodiscard]] uint32_t px(uint32_t i) const noexcept { return x + dx[i]; }
    [[nodiscard]] uint32_t py(uint32_t i) const noexcept { return y + dy[i]; }
};

/// Per-tile working memory, one per worker thread for the whole render (~30 KB): the tile loop
/// never allocates or re-initialises it.
struct TileScratch {
    TilePixels tile;
    std::array<Ray, kMaxTilePixels> rays;
    std::array<Hit, kMaxTilePixels> hits;
    std::array<uint8_t, kMaxTilePixels> occluded;
    std::array<Surface, kMaxTilePixels> surfaces;     ///< per live path / AO point
    std::array<uint16_t, kMaxTilePixels> path_pixel;  ///< tile pixel of each live path
    std::array<float, kMaxTilePixels> throughput;     ///< per live path
    std::array<uint16_t, kMaxTilePixels> ray_path;    ///< path of each ray in `rays`
    std::array<float, kMaxTilePixels> ray_weight;     ///< per ray: light or throughput weight
    std::array<float, kMaxTilePixels> value;          ///< per tile pixel: this sample's grey value
    std::array<std::array<float, 4>, kMaxTilePixels> sum;  ///< per tile pixel: RGB + coverage
    std::array<uint32_t, kMaxTilePixels> geoms;  ///< scene renders: the geometry id of hits[i]
};

/// The world-space triangle of hit i of `s`.
inline TriVerts Frame::triangle(const TileScratch& s, uint32_t i) const noexcept {
    return scene ? world_triangle(*scene, s.geoms[i], s.hits[i].prim)
                 : tree->triangle(s.hits[i].prim);
}

}  // namespace kdrt::detail
