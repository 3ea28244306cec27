// render(): the tile loop (tiles in parallel over the calling thread's oneTBB arena, each traced
// as blocks of Morton-ordered rays and shaded by render_shading.h), progress and cancellation.

#include "kdrt/render.h"

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <mutex>
#include <span>
#include <string>

#include "kdrt/scene.h"
#include "kdrt/trace.h"
#include "render_frame.h"
#include "render_internal.h"
#include "render_shading.h"

namespace kdrt {
namespace {

using detail::Frame;
using detail::kMaxTilePixels;
using detail::kMaxTileSize;
using detail::make_frame;
using detail::render_fail;
using detail::shade_ao;
using detail::shade_diffuse;
using detail::shade_primary;
using detail::TilePixels;
using detail::TileScratch;

using Clock = std::chrono::steady_clock;

// Progress is reported about this many times per render.
constexpr uint64_t kProgressSteps = 256;

// ---------------------------------------------------------------------------------------------
// Tracing

/// The tree's own block queries: direct calls, no indirection per block or ray. A mesh has no
/// geometry ids (Frame::triangle does not read them).
struct TreeTracer {
    const KdTree& tree;
    void intersect(std::span<const Ray> rays, std::span<Hit> hits,
                   std::span<uint32_t> /*geoms*/) const noexcept {
        intersect_block(tree, rays, hits);
    }
    void occluded(std::span<const Ray> rays, std::span<uint8_t> out) const noexcept {
        occluded_block(tree, rays, out);
    }
};

/// Queries through caller-supplied functions (tests: the brute-force oracle), one call per block.
struct FunctionTracer {
    const detail::TraceFunctions& functions;
    void intersect(std::span<const Ray> rays, std::span<Hit> hits,
                   std::span<uint32_t> /*geoms*/) const noexcept {
        functions.intersect(functions.context, rays, hits);
    }
    void occluded(std::span<const Ray> rays, std::span<uint8_t> out) const noexcept {
        functions.occluded(functions.context, rays, out);
    }
};

/// A scene's block queries (kdrt/scene.h): the mesh-level part of each answer into `hits`, the
/// geometry ids into `geoms`. Blocks are at most a tile's pixels.
struct SceneTracer {
    const Scene& scene;
    void intersect(std::span<const Ray> rays, std::span<Hit> hits,
                   std::span<uint32_t> geoms) const noexcept {
        std::array<SceneHit, detail::kMaxTilePixels> answers;
        const std::span<SceneHit> out(answers.data(), rays.size());
        intersect_block(scene, rays, out);
        for (size_t i = 0; i < rays.size(); ++i) {
            hits[i] = out[i].hit();
            geoms[i] = out[i].geom;
        }
    }
    void occluded(std::span<const Ray> rays, std::span<uint8_t> out) const noexcept {
        occluded_block(scene, rays, out);
    }
};

/// Pixel order inside a tile: Morton (Z) order, so every 4, 16 and 64 consecutive rays of a
/// tile's block form 2x2, 4x4 and 8x8 squares (8 and 32 form 4x2 and 8x4 rectangles). The packet
/// engine takes consecutive rays as packets: square packets are the most coherent.
struct MortonTable {
    std::array<uint8_t, kMaxTilePixels> x;
    std::array<uint8_t, kMaxTilePixels> y;
};

constexpr MortonTable make_morton_table() noexcept {
    MortonTable table{};
    for (uint32_t i = 0; i < kMaxTilePixels; ++i) {
        uint32_t x = 0, y = 0;
        for (uint32_t bit = 0; bit < 4; ++bit) {
            x |= ((i >> (2 * bit)) & 1u) << bit;
            y |= ((i >> (2 * bit + 1)) & 1u) << bit;
        }
        table.x[i] = static_cast<uint8_t>(x);
        table.y[i] = static_cast<uint8_t>(y);
    }
    return table;
}

constexpr MortonTable kMorton = make_morton_table();
static_assert(kMorton.x[63] == 7 && kMorton.y[63] == 7, "the first 64 entries cover an 8x8 tile");

/// Renders one tile into `image`; returns the rays traced.
template <class Tracer>
uint64_t render_tile(const Frame& f, const Tracer& tracer, uint32_t tile_index, TileScratch& s,
                     Image& image) noexcept {
    const uint32_t size = f.settings.tile_size;
    const uint32_t col = tile_index % f.tiles_x, row = tile_index / f.tiles_x;
    const uint32_t x0 = col * size, y0 = row * size;  // region coordinates
    const uint32_t width = std::min(size, f.region.width - x0),
                   height = std::min(size, f.region.height - y0);
    TilePixels& tile = s.tile;
    tile.x = f.region.x + x0;
    tile.y = f.region.y + y0;
    uint32_t n = 0;
    if (width == size && height == size) {
        n = size * size;
        std::copy_n(kMorton.x.begin(), n, tile.dx.begin());
        std::copy_n(kMorton.y.begin(), n, tile.dy.begin());
    } else {
        for (uint32_t m = 0; m < size * size;
             ++m) {  // edge tiles keep the Morton order of their pixels
            if (kMorton.x[m] >= width || kMorton.y[m] >= height) continue;
            tile.dx[n] = kMorton.x[m];
            tile.dy[n] = kMorton.y[m];
            ++n;
        }
    }
    tile.count = n;
    std::fill_n(s.sum.begin(), n, std::array<float, 4>{0.0f, 0.0f, 0.0f, 0.0f});

    uint64_t rays = 0;
    for (uint32_t sample = 0; sample < f.settings.spp; ++sample) {
        if (f.settings.spp == 1) {
            // Pixel centres: the image-plane coordinates depend on the column or the row alone.
            std::array<float, kMaxTileSize> sx, sy;
            for (uint32_t c = 0; c < width; ++c)
                sx[c] = f.camera.plane_x(static_cast<float>(tile.x + c) + 0.5f);
            for (uint32_t r = 0; r < height; ++r)
                sy[r] = f.camera.plane_y(static_cast<float>(tile.y + r) + 0.5f);
            for (uint32_t i = 0; i < n; ++i)
                s.rays[i] = f.camera.ray_at(sx[tile.dx[i]], sy[tile.dy[i]]);
        } else {
            for (uint32_t i = 0; i < n; ++i)
                s.rays[i] = f.camera_ray(tile.px(i), tile.py(i), sample);
        }
        tracer.intersect(std::span<const Ray>(s.rays.data(), n), std::span<Hit>(s.hits.data(), n),
                         std::span<uint32_t>(s.geoms.data(), n));
        rays += n;
        switch (f.settings.shading) {
            case Shading::kAo:
                rays += shade_ao(f, tracer, tile, sample, s);
                break;
            case Shading::kDiffuse:
                rays += shade_diffuse(f, tracer, tile, sample, s);
                break;
            case Shading::kNormals:
                shade_primary<Shading::kNormals>(f, tile, s);
                break;
            case Shading::kEyelight:
                shade_primary<Shading::kEyelight>(f, tile, s);
                break;
            case Shading::kDepth:
                shade_primary<Shading::kDepth>(f, tile, s);
                break;
            case Shading::kPrimId:
                shade_primary<Shading::kPrimId>(f, tile, s);
                break;
            case Shading::kGeomId:
                shade_primary<Shading::kGeomId>(f, tile, s);
                break;
        }
    }

    // The pixel is the average of its samples; x / 1 == x, so one sample skips the divisions.
    const auto spp = static_cast<float>(f.settings.spp);
    const bool alpha = f.channels == 4;
    float* pixels = image.pixels.data();
    for (uint32_t i = 0; i < n; ++i) {
        float* out =
            pixels + (size_t{y0 + tile.dy[i]} * f.region.width + x0 + tile.dx[i]) * f.channels;
        const std::array<float, 4>& sum = s.sum[i];
        if (f.settings.spp == 1) {
            out[0] = sum[0];
            out[1] = sum[1];
            out[2] = sum[2];
            if (alpha) out[3] = sum[3];
        } else {
            out[0] = sum[0] / spp;
            out[1] = sum[1] / spp;
            out[2] = sum[2] / spp;
            if (alpha) out[3] = sum[3] / spp;
        }
    }
    return rays;
}

/// Serialises progress reports from the workers: increasing values, about kProgressSteps of
/// them, never blocking a worker (a busy reporter means someone else is reporting).
class ProgressReporter {
public:
    ProgressReporter(const std::function<void(double)>& callback, uint64_t total) noexcept
        : callback_(callback),
          total_(total),
          step_((total + kProgressSteps - 1) / kProgressSteps) {}

    void tile_done() {
        if (!callback_) return;
        const uint64_t done = done_.fetch_add(1, std::memory_order_relaxed) + 1;
        if (done >= total_ || done < next_.load(std::memory_order_relaxed))
            return;  // 1.0 comes from finish()
        const std::unique_lock lock(mutex_, std::try_to_lock);
        if (!lock.owns_lock() || done <= reported_) return;
        reported_ = done;
        next_.store(done + step_, std::memory_order_relaxed);
        callback_(static_cast<double>(done) / static_cast<double>(total_));
    }

    void finish() {
        if (!callback_) return;
        const std::lock_guard lock(mutex_);
        callback_(1.0);
    }

private:
    const std::function<void(double)>& callback_;
    const uint64_t total_;
    const uint64_t step_;
    std::atomic<uint64_t> done_{0};
    std::atomic<uint64_t> next_{0};
    std::mutex mutex_;
    uint64_t reported_ = 0;
};

template <class Tracer>
Image render_frame(const KdTree* tree, const Scene* scene, const RenderSettings& settings,
                   const Tracer& tracer, const RenderControl& control, RenderStats* stats) {
    const auto start = Clock::now();
    const Frame frame = make_frame(tree, scene, settings);
    Image image;
    image.width = frame.region.width;
    image.height = frame.region.height;
    image.channels = frame.channels;
    // Every tile writes each of its pixels (render_tile), so nothing writes the frame first.
    image.pixels = uninitialized_pixels(size_t{image.width} * image.height * image.channels);

    const uint32_t tile_count = frame.tiles_x * frame.tiles_y;
    ProgressReporter progress(control.progress, tile_count);
    std::atomic<uint64_t> ray_count{0};
    std::atomic<bool> skipped{false};
    tbb::enumerable_thread_specific<TileScratch> scratch_per_thread;
    tbb::parallel_for(
        tbb::blocked_range<uint32_t>(0, tile_count),
        [&](const tbb::blocked_range<uint32_t>& range) {
            TileScratch& scratch = scratch_per_thread.local();
            uint64_t rays = 0;
            for (uint32_t t = range.begin(); t != range.end(); ++t) {
                if (control.cancel && control.cancel->load(std::memory_order_relaxed)) {
                    skipped.store(true, std::memory_order_relaxed);
                    break;
                }
                rays += render_tile(frame, tracer, t, scratch, image);
                progress.tile_done();
            }
            ray_count.fetch_add(rays, std::memory_order_relaxed);
        });
    if (skipped.load())
        throw RenderCancelled("render cancelled before all " + std::to_string(tile_count) +
                              " tiles were done");
    progress.finish();

    if (stats) {
        stats->pixels = uint64_t{image.width} * image.height;
        stats->tiles = tile_count;
        stats->primary_rays = stats->pixels * settings.spp;
        stats->rays = ray_count.load();
        stats->seconds = std::chrono::duration<double>(Clock::now() - start).count();
    }
    return image;
}

}  // namespace

Image render(const KdTree& tree, const RenderSettings& settings, const RenderControl& control,
             RenderStats* stats) {
    return render_frame(&tree, nullptr, settings, TreeTracer{tree}, control, stats);
}

Image render(const Scene& scene, const RenderSettings& settings, const RenderControl& control,
             RenderStats* stats) {
    return render_frame(nullptr, &scene, settings, SceneTracer{scene}, control, stats);
}

std::vector<Ray> render_camera_rays(const KdTree& tree, const RenderSettings& settings,
                                    uint32_t sample) {
    const Frame frame = make_frame(&tree, nullptr, settings);
    if (sample >= settings.spp) {
        render_fail("camera ray sample " + std::to_string(sample) + " must be below spp " +
                    std::to_string(settings.spp));
    }
    std::vector<Ray> rays;
    rays.reserve(size_t{frame.region.width} * frame.region.height);
    for (uint32_t y = 0; y < frame.region.height; ++y) {
        for (uint32_t x = 0; x < frame.region.width; ++x) {
            rays.push_back(frame.camera_ray(frame.region.x + x, frame.region.y + y, sample));
        }
    }
    return rays;
}

namespace detail {

Image render_with(const KdTree& tree, const RenderSettings& settings, const TraceFunctions& trace,
                  const RenderControl& control, RenderStats* stats) {
    return render_frame(&tree, nullptr, settings, FunctionTracer{trace}, control, stats);
}

}  // namespace detail
}  // namespace kdrt
