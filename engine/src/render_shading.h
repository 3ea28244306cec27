#pragma once
// Internal: the shading modes of the renderer, one function per mode family, each shading the
// camera hits of one tile and sample (TileScratch::hits) into TileScratch::sum. `Tracer` answers
// blocks of secondary rays (intersect / occluded with the contract of intersect_block).

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <span>

#include "geometry.h"
#include "random.h"
#include "render_frame.h"
#include "sampling.h"

namespace kdrt::detail {

inline constexpr float kShadeInf = std::numeric_limits<float>::infinity();
// Paths that have bounced this often play Russian roulette before the next bounce: the first
// bounces carry most of the indirect light, so they are always traced.
inline constexpr uint32_t kRouletteStartBounce = 2;
// Even a bright path stops with probability 5% per bounce, which bounds the expected length.
inline constexpr float kMaxSurvival = 0.95f;
// A shadow ray towards a point light stops this short of the light (relative), so the segment
// never reaches geometry the light sits on.
inline constexpr float kPointLightReach = 0.999f;

/// facing_normal (geometry.h) in float, for display only (normals and eyelight): a camera hit's
/// colour tolerates the float rounding of sliver triangles, and this is the renderer's per-pixel
/// cost.
inline Vec3 display_normal(const TriVerts& tri, Vec3 dir) noexcept {
    const Vec3 v0{tri.v0[0], tri.v0[1], tri.v0[2]};
    const Vec3 n = cross(Vec3{tri.v1[0], tri.v1[1], tri.v1[2]} - v0,
                         Vec3{tri.v2[0], tri.v2[1], tri.v2[2]} - v0);
    const float len2 = dot(n, n);
    if (!(len2 > 0.0f) || !std::isfinite(len2))
        return facing_normal<NormalScaling::kReciprocal>(tri, dir);  // tiny, huge or degenerate
    const Vec3 normal = n * (1.0f / std::sqrt(len2));
    return dot(normal, dir) > 0.0f ? normal * -1.0f : normal;
}

/// A fixed colour per triangle id (and geometry id, in a scene; 0 for a mesh): three bytes of a
/// hash of both.
inline std::array<float, 3> prim_colour(uint32_t prim, uint32_t geom) noexcept {
    const uint64_t h = mix64(0x6B64727450726D49ull ^ (uint64_t{geom} << 32 | prim));
    return {static_cast<float>(h & 0xFFu) / 255.0f, static_cast<float>((h >> 8) & 0xFFu) / 255.0f,
            static_cast<float>((h >> 16) & 0xFFu) / 255.0f};
}

/// A fixed colour per geometry id alone (a scene's instance; 0 for a mesh): three bytes of a hash
/// of the id, another hash than prim_colour's, so every triangle of an instance has its colour.
inline std::array<float, 3> geom_colour(uint32_t geom) noexcept {
    const uint64_t h = mix64(0x6B64727447656F6Dull ^ uint64_t{geom});
    return {static_cast<float>(h & 0xFFu) / 255.0f, static_cast<float>((h >> 8) & 0xFFu) / 255.0f,
            static_cast<float>((h >> 16) & 0xFFu) / 255.0f};
}

inline void add(std::array<float, 4>& sum, float r, float g, float b, float coverage) noexcept {
    sum[0] += r;
    sum[1] += g;
    sum[2] += b;
    sum[3] += coverage;
}

inline void add_background(const Frame& f, std::array<float, 4>& sum) noexcept {
    add(sum, f.settings.background.x, f.settings.background.y, f.settings.background.z, 0.0f);
}

/// normals, eyelight, depth, primid, geomid: a colour straight from the camera hit. One loop per
/// mode, so the per-pixel loop has no mode switch.
template <Shading kShading>
void shade_primary(const Frame& f, const TilePixels& tile, TileScratch& s) noexcept {
    for (uint32_t i = 0; i < tile.pixel_count(); ++i) {
        const Hit& hit = s.hits[i];
        if (!hit.is_hit()) {
            add_background(f, s.sum[i]);
            continue;
        }
        if constexpr (kShading == Shading::kNormals) {
            const Vec3 n = display_normal(f.triangle(s, i), direction(s.rays[i]));
            add(s.sum[i], 0.5f * n.x + 0.5f, 0.5f * n.y + 0.5f, 0.5f * n.z + 0.5f, 1.0f);
        } else if constexpr (kShading == Shading::kEyelight) {
            const Vec3 d = direction(s.rays[i]);
            // Camera directions are unit vectors; the clamp only absorbs rounding.
            const float c = std::min(1.0f, std::fabs(dot(display_normal(f.triangle(s, i), d), d)));
            add(s.sum[i], c, c, c, 1.0f);
        } else if constexpr (kShading == Shading::kDepth) {
            add(s.sum[i], hit.t, hit.t, hit.t, 1.0f);
        } else if constexpr (kShading == Shading::kPrimId) {
            const auto c = prim_colour(hit.prim, f.scene ? s.geoms[i] : 0u);
            add(s.sum[i], c[0], c[1], c[2], 1.0f);
        } else {
            static_assert(kShading == Shading::kGeomId);
            const auto c = geom_colour(f.scene ? s.geoms[i] : 0u);
            add(s.sum[i], c[0], c[1], c[2], 1.0f);
        }
    }
}

/// Collects the camera hits of the tile as surfaces (misses get the background). Returns the
/// number of hits.
inline uint32_t gather_surfaces(const Frame& f, const TilePixels& tile, TileScratch& s) noexcept {
    uint32_t count = 0;
    for (uint32_t i = 0; i < tile.pixel_count(); ++i) {
        if (!s.hits[i].is_hit()) {
            add_background(f, s.sum[i]);
            continue;
        }
        s.surfaces[count] = surface_at<NormalScaling::kReciprocal>(f.triangle(s, i), s.rays[i],
                                                                   s.hits[i], f.offset);
        s.path_pixel[count] = static_cast<uint16_t>(i);
        ++count;
    }
    return count;
}

template <class Tracer>
uint64_t shade_ao(const Frame& f, const Tracer& tracer, const TilePixels& tile, uint32_t sample,
                  TileScratch& s) noexcept {
    const uint32_t count = gather_surfaces(f, tile, s);
    if (count == 0) return 0;
    const uint32_t k = f.settings.ao_samples;
    std::fill_n(s.value.begin(), count, 0.0f);
    for (uint32_t j = 0; j < k; ++j) {
        for (uint32_t p = 0; p < count; ++p) {
            const uint32_t i = s.path_pixel[p];
            CounterRng rng =
                pixel_rng(f.settings.seed, tile.px(i), tile.py(i), sample, PixelStream::kAo, j);
            const Surface& surface = s.surfaces[p];
            const Vec3 d = cosine_direction(surface.normal, rng);
            s.rays[p] =
                Ray{surface.origin.x, surface.origin.y, surface.origin.z, 0.0f, d.x, d.y, d.z,
                    f.ao_tmax};
        }
        tracer.occluded(std::span<const Ray>(s.rays.data(), count),
                        std::span<uint8_t>(s.occluded.data(), count));
        for (uint32_t p = 0; p < count; ++p) s.value[p] += s.occluded[p] ? 0.0f : 1.0f;
    }
    for (uint32_t p = 0; p < count; ++p) {
        const float v = s.value[p] / static_cast<float>(k);
        add(s.sum[s.path_pixel[p]], v, v, v, 1.0f);
    }
    return uint64_t{count} * k;
}

/// Direct light at every live path vertex: one shadow ray per vertex that faces the light.
template <class Tracer>
uint64_t add_direct_light(const Frame& f, const Tracer& tracer, uint32_t paths,
                          TileScratch& s) noexcept {
    const Light& light = f.settings.light;
    uint32_t count = 0;
    for (uint32_t p = 0; p < paths; ++p) {
        const Surface& surface = s.surfaces[p];
        Vec3 dir = f.to_light;
        float weight = light.intensity;
        float tmax = kShadeInf;
        if (light.kind == LightKind::kPoint) {
            const Vec3 to_light = light.position - surface.origin;
            const float distance2 = dot(to_light, to_light);
            if (!(distance2 > 0.0f) || !std::isfinite(distance2)) continue;
            const float distance = std::sqrt(distance2);
            dir = to_light * (1.0f / distance);
            weight = light.intensity / distance2;
            tmax = distance * kPointLightReach;
        }
        const float cosine = dot(surface.normal, dir);
        if (!(cosine > 0.0f)) continue;
        s.rays[count] = Ray{
            surface.origin.x, surface.origin.y, surface.origin.z, 0.0f, dir.x, dir.y, dir.z, tmax};
        s.ray_path[count] = static_cast<uint16_t>(p);
        s.ray_weight[count] = weight * cosine;
        ++count;
    }
    if (count == 0) return 0;
    tracer.occluded(std::span<const Ray>(s.rays.data(), count),
                    std::span<uint8_t>(s.occluded.data(), count));
    for (uint32_t r = 0; r < count; ++r) {
        if (s.occluded[r]) continue;
        const uint32_t p = s.ray_path[r];
        s.value[s.path_pixel[p]] += s.throughput[p] * f.settings.albedo * s.ray_weight[r];
    }
    return count;
}

/// Lambertian paths: direct light with a shadow ray at every vertex (next-event estimation),
/// cosine-weighted continuation (the cosine and 1/pi of the BRDF cancel against the pdf, so the
/// throughput just takes the albedo), Russian roulette from kRouletteStartBounce on.
template <class Tracer>
uint64_t shade_diffuse(const Frame& f, const Tracer& tracer, const TilePixels& tile,
                       uint32_t sample, TileScratch& s) noexcept {
    uint32_t paths = gather_surfaces(f, tile, s);
    uint64_t rays = 0;
    for (uint32_t p = 0; p < paths; ++p) {
        s.throughput[p] = 1.0f;
        s.value[s.path_pixel[p]] = 0.0f;
    }
    // The hit pixels, remembered before the compaction below reorders path_pixel.
    std::array<uint16_t, kMaxTilePixels> hit_pixels;
    const uint32_t hit_count = paths;
    std::copy_n(s.path_pixel.begin(), hit_count, hit_pixels.begin());

    for (uint32_t bounce = 0; paths > 0; ++bounce) {
        rays += add_direct_light(f, tracer, paths, s);
        if (bounce == f.settings.bounces) break;
        uint32_t count = 0;
        for (uint32_t p = 0; p < paths; ++p) {
            const uint32_t i = s.path_pixel[p];
            CounterRng rng = pixel_rng(f.settings.seed, tile.px(i), tile.py(i), sample,
                                       PixelStream::kBounce, bounce);
            float throughput = s.throughput[p] * f.settings.albedo;
            if (bounce >= kRouletteStartBounce) {
                const float survival = std::min(throughput, kMaxSurvival);
                if (!(rng.uniform() < survival)) continue;
                throughput /= survival;
            }
            if (!(throughput > 0.0f)) continue;
            const Surface& surface = s.surfaces[p];
            const Vec3 d = cosine_direction(surface.normal, rng);
            s.rays[count] =
                Ray{surface.origin.x, surface.origin.y, surface.origin.z, 0.0f, d.x, d.y, d.z,
                    kShadeInf};
            s.ray_path[count] = static_cast<uint16_t>(p);
            s.ray_weight[count] = throughput;
            ++count;
        }
        if (count == 0) break;
        tracer.intersect(std::span<const Ray>(s.rays.data(), count),
                         std::span<Hit>(s.hits.data(), count),
                         std::span<uint32_t>(s.geoms.data(), count));
        rays += count;
        // Compact the surviving paths in place: ray r belongs to path ray_path[r] >= r >= the
        // slot written, so every slot is read before it is overwritten.
        uint32_t live = 0;
        for (uint32_t r = 0; r < count; ++r) {
            const uint32_t pixel = s.path_pixel[s.ray_path[r]];
            if (!s.hits[r].is_hit()) {
                s.value[pixel] += s.ray_weight[r] * f.settings.sky;
                continue;
            }
            s.surfaces[live] = surface_at<NormalScaling::kReciprocal>(f.triangle(s, r), s.rays[r],
                                                                      s.hits[r], f.offset);
            s.path_pixel[live] = static_cast<uint16_t>(pixel);
            s.throughput[live] = s.ray_weight[r];
            ++live;
        }
        paths = live;
    }
    for (uint32_t h = 0; h < hit_count; ++h) {
        const float v = s.value[hit_pixels[h]];
        add(s.sum[hit_pixels[h]], v, v, v, 1.0f);
    }
    return rays;
}

}  // namespace kdrt::detail
