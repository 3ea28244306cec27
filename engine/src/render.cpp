#include "kdrt/render.h"

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <mutex>
#include <span>
#include <string>

#include "kdrt/trace.h"
#include "render_internal.h"
#include "sampling.h"

namespace kdrt {
namespace {

using detail::cosine_direction;
using detail::is_finite;
using detail::normalized;

using Clock = std::chrono::steady_clock;

constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr uint32_t kMaxTileSize = 16;
constexpr uint32_t kMaxTilePixels = kMaxTileSize * kMaxTileSize;
// Paths that have bounced this often play Russian roulette before the next bounce: the first
// bounces carry most of the indirect light, so they are always traced.
constexpr uint32_t kRouletteStartBounce = 2;
// Even a bright path stops with probability 5% per bounce, which bounds the expected length.
constexpr float kMaxSurvival = 0.95f;
// A shadow ray towards a point light stops this short of the light (relative), so the segment
// never reaches geometry the light sits on.
constexpr float kPointLightReach = 0.999f;
// Progress is reported about this many times per render.
constexpr uint64_t kProgressSteps = 256;

// ---------------------------------------------------------------------------------------------
// Counter-based random numbers

// splitmix64 finaliser (Steele, Lea & Flood 2014): a bijection on 64 bits with good avalanche.
constexpr uint64_t mix64(uint64_t x) noexcept {
    x += 0x9E3779B97F4A7C15ull;
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
    return x ^ (x >> 31);
}

/// What a random stream is used for; part of its key, so streams never overlap.
enum class Stream : uint32_t {
    kStrata = 0,  ///< the pixel's permutation of the stratification cells
    kJitter = 1,  ///< position of one camera sample inside its cell
    kAo = 2,      ///< one AO ray (index = AO ray number)
    kBounce = 3,  ///< one bounce of a path (index = bounce number): roulette, direction
};

/// Random numbers keyed by (seed, full-frame pixel, sample, stream, index): the same values
/// whichever thread, tile or region computes the pixel.
class PixelRng {
public:
    PixelRng(uint64_t seed, uint32_t x, uint32_t y, uint32_t sample, Stream stream,
             uint32_t index) noexcept
        : state_(mix64(mix64(mix64(seed) ^ ((uint64_t{y} << 32) | x)) ^
                       ((uint64_t{sample} << 32) | (uint64_t{static_cast<uint32_t>(stream)} << 28) |
                        index))) {}

    uint32_t bits() noexcept {
        state_ += 0x9E3779B97F4A7C15ull;
        return static_cast<uint32_t>(mix64(state_) >> 32);
    }
    /// Uniform in [0, 1): 24 random bits, so every value is an exact float.
    float uniform() noexcept { return static_cast<float>(bits() >> 8) * 0x1.0p-24f; }
    /// Uniform in [-1, 1).
    float symmetric() noexcept { return 2.0f * uniform() - 1.0f; }

private:
    uint64_t state_;
};

/// A permutation of [0, count) chosen by `key`, evaluated at `index` < count: a keyed bijection
/// of [0, 2^k) (xor, odd multiplications and xorshifts, all mod 2^k), repeated until the value
/// lands below count ("cycle walking"; it ends because index itself is below count).
uint32_t permute(uint32_t index, uint32_t count, uint32_t key) noexcept {
    const uint32_t mask = std::bit_ceil(count) - 1u;
    const int shift = std::max(1, std::popcount(mask) / 2);
    uint32_t i = index;
    do {
        i = (i ^ key) & mask;
        i = (i * 0x2C1B3C6Du) & mask;
        i ^= i >> shift;
        i = (i + (key >> 16)) & mask;
        i = (i * 0x297A2D39u) & mask;
        i ^= i >> shift;
    } while (i >= count);
    return i;
}

// ---------------------------------------------------------------------------------------------
// Geometry

Vec3 direction(const Ray& r) noexcept { return {r.dx, r.dy, r.dz}; }

/// Unit geometric normal of `tri` facing against `dir` (towards where the ray came from), for
/// spawning secondary rays. The cross product is taken in double: sliver triangles lose most bits
/// of it in float, and a wrong side would start AO and bounce rays inside the surface.
Vec3 facing_normal(const TriVerts& tri, Vec3 dir) noexcept {
    const double e1[3] = {double{tri.v1[0]} - tri.v0[0], double{tri.v1[1]} - tri.v0[1],
                          double{tri.v1[2]} - tri.v0[2]};
    const double e2[3] = {double{tri.v2[0]} - tri.v0[0], double{tri.v2[1]} - tri.v0[1],
                          double{tri.v2[2]} - tri.v0[2]};
    const double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                         e1[0] * e2[1] - e1[1] * e2[0]};
    const double len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    if (!(len > 0.0) || !std::isfinite(len)) {
        // The engine never reports hits on zero-area triangles; stay well defined regardless.
        return normalized(dir) * -1.0f;
    }
    const double inv_len = 1.0 / len;
    Vec3 normal{static_cast<float>(n[0] * inv_len), static_cast<float>(n[1] * inv_len),
                static_cast<float>(n[2] * inv_len)};
    if (dot(normal, dir) > 0.0f) normal = normal * -1.0f;
    return normal;
}

/// The same normal in float, for display only (normals and eyelight): a camera hit's colour
/// tolerates the float rounding of sliver triangles, and this is the renderer's per-pixel cost.
Vec3 display_normal(const TriVerts& tri, Vec3 dir) noexcept {
    const Vec3 v0{tri.v0[0], tri.v0[1], tri.v0[2]};
    const Vec3 n = cross(Vec3{tri.v1[0], tri.v1[1], tri.v1[2]} - v0,
                         Vec3{tri.v2[0], tri.v2[1], tri.v2[2]} - v0);
    const float len2 = dot(n, n);
    if (!(len2 > 0.0f) || !std::isfinite(len2))
        return facing_normal(tri, dir);  // tiny, huge or degenerate
    const Vec3 normal = n * (1.0f / std::sqrt(len2));
    return dot(normal, dir) > 0.0f ? normal * -1.0f : normal;
}

/// A hit, prepared for spawning secondary rays.
struct Surface {
    Vec3 origin;  ///< the hit point, pushed off the surface along `normal`
    Vec3 normal;  ///< unit geometric normal on the side the ray came from
};

Surface surface_at(std::span<const TriVerts> tris, const Ray& ray, const Hit& hit,
                   float offset) noexcept {
    const TriVerts& tri = tris[hit.prim];
    const Vec3 v0{tri.v0[0], tri.v0[1], tri.v0[2]};
    const Vec3 v1{tri.v1[0], tri.v1[1], tri.v1[2]};
    const Vec3 v2{tri.v2[0], tri.v2[1], tri.v2[2]};
    // The barycentric point lies on the triangle to rounding; o + t*d can be off by |t*d| ulps.
    const Vec3 p = v0 * (1.0f - hit.u - hit.v) + v1 * hit.u + v2 * hit.v;
    const Vec3 normal = facing_normal(tri, direction(ray));
    return {p + normal * offset, normal};
}

/// A fixed colour per triangle id: three bytes of a hash of the id.
std::array<float, 3> prim_colour(uint32_t prim) noexcept {
    const uint64_t h = mix64(0x6B64727450726D49ull ^ prim);
    return {static_cast<float>(h & 0xFFu) / 255.0f, static_cast<float>((h >> 8) & 0xFFu) / 255.0f,
            static_cast<float>((h >> 16) & 0xFFu) / 255.0f};
}

// ---------------------------------------------------------------------------------------------
// Settings

std::string format_float(float value) {
    char text[32];
    std::snprintf(text, sizeof text, "%g", static_cast<double>(value));
    return text;
}

std::string format_vec(Vec3 v) {
    // Appended piecewise: GCC 12 warns (-Wrestrict, a false positive) on "(" + std::string.
    std::string text(1, '(');
    text += format_float(v.x);
    text += ", ";
    text += format_float(v.y);
    text += ", ";
    text += format_float(v.z);
    text += ')';
    return text;
}

[[noreturn]] void fail(const std::string& message) { throw RenderError("render " + message); }

void require_range(const char* field, uint64_t value, uint64_t lo, uint64_t hi) {
    if (value < lo || value > hi) {
        fail(std::string(field) + " " + std::to_string(value) + " must be in " +
             std::to_string(lo) + " .. " + std::to_string(hi));
    }
}

void require_finite_nonnegative(const char* field, float value) {
    if (!(value >= 0.0f) || !std::isfinite(value)) {
        fail(std::string(field) + " " + format_float(value) + " must be a finite value >= 0");
    }
}

/// The box secondary rays and the default camera work with: the tree bounds, or the unit cube
/// around the origin for an empty tree (default_camera's fallback too).
Aabb scene_box(const KdTree& tree) noexcept {
    if (!tree.bounds.empty() && is_finite(tree.bounds.lo) && is_finite(tree.bounds.hi))
        return tree.bounds;
    return Aabb{{-0.5f, -0.5f, -0.5f}, {0.5f, 0.5f, 0.5f}};
}

PixelRegion region_of(const RenderSettings& s) noexcept {
    return s.region ? *s.region : PixelRegion{0, 0, s.width, s.height};
}

Camera make_camera(const KdTree& tree, const RenderSettings& s) {
    try {
        const CameraSpec spec =
            s.camera
                ? *s.camera
                : default_camera(tree.bounds, static_cast<float>(static_cast<double>(s.width) /
                                                                 static_cast<double>(s.height)));
        return Camera(spec, s.width, s.height);
    } catch (const CameraError& e) {
        throw RenderError(e.what());
    }
}

/// The stratification grid of `spp` samples: columns x rows cells, columns * rows >= spp.
struct SampleGrid {
    uint32_t columns = 1;
    uint32_t rows = 1;
};

SampleGrid sample_grid(uint32_t spp) noexcept {
    auto columns = static_cast<uint32_t>(std::sqrt(static_cast<double>(spp)));
    while (columns * columns < spp) ++columns;
    while (columns > 1 && (columns - 1) * (columns - 1) >= spp) --columns;
    return {columns, (spp + columns - 1) / columns};
}

/// Everything fixed for one render.
struct Frame {
    const RenderSettings& settings;
    Camera camera;
    PixelRegion region;
    std::span<const TriVerts> tris;
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
            const uint32_t key = PixelRng(settings.seed, x, y, 0, Stream::kStrata, 0).bits();
            const uint32_t cell = permute(sample, grid.columns * grid.rows, key);
            PixelRng rng(settings.seed, x, y, sample, Stream::kJitter, 0);
            const float u1 = rng.uniform(), u2 = rng.uniform();
            jx = (static_cast<float>(cell % grid.columns) + u1) / static_cast<float>(grid.columns);
            jy = (static_cast<float>(cell / grid.columns) + u2) / static_cast<float>(grid.rows);
        }
        return camera.ray(static_cast<float>(x) + jx, static_cast<float>(y) + jy);
    }
};

Frame make_frame(const KdTree& tree, const RenderSettings& s) {
    validate_render_settings(s);
    const Aabb box = scene_box(tree);
    const Vec3 ext = box.extent();
    const float diag = std::sqrt(dot(ext, ext));
    float magnitude = 0.0f;
    for (int a = 0; a < 3; ++a)
        magnitude = std::max({magnitude, std::fabs(box.lo[a]), std::fabs(box.hi[a])});
    const PixelRegion region = region_of(s);
    const uint32_t tile = s.tile_size;
    return Frame{
        .settings = s,
        .camera = make_camera(tree, s),
        .region = region,
        .tris = tree.tris,
        .channels = s.alpha ? 4u : 3u,
        .tiles_x = (region.width + tile - 1) / tile,
        .tiles_y = (region.height + tile - 1) / tile,
        .grid = sample_grid(s.spp),
        // About 100 ulps of the largest coordinate, far below the size of any visible triangle
        // (the same offset the ray-set generator uses).
        .offset = 1e-5f * (diag + magnitude),
        .ao_tmax = s.ao_distance * diag,
        .to_light =
            s.light.kind == LightKind::kDirectional ? normalized(s.light.direction) : Vec3{},
    };
}

// ---------------------------------------------------------------------------------------------
// Tracing

/// The tree's own block queries: direct calls, no indirection per block or ray.
struct TreeTracer {
    const KdTree& tree;
    void intersect(std::span<const Ray> rays, std::span<Hit> hits) const noexcept {
        intersect_block(tree, rays, hits);
    }
    void occluded(std::span<const Ray> rays, std::span<uint8_t> out) const noexcept {
        occluded_block(tree, rays, out);
    }
};

/// Queries through caller-supplied functions (tests: the brute-force oracle), one call per block.
struct FunctionTracer {
    const detail::TraceFunctions& functions;
    void intersect(std::span<const Ray> rays, std::span<Hit> hits) const noexcept {
        functions.intersect(functions.context, rays, hits);
    }
    void occluded(std::span<const Ray> rays, std::span<uint8_t> out) const noexcept {
        functions.occluded(functions.context, rays, out);
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
};

void add(std::array<float, 4>& sum, float r, float g, float b, float coverage) noexcept {
    sum[0] += r;
    sum[1] += g;
    sum[2] += b;
    sum[3] += coverage;
}

void add_background(const Frame& f, std::array<float, 4>& sum) noexcept {
    add(sum, f.settings.background.x, f.settings.background.y, f.settings.background.z, 0.0f);
}

/// normals, eyelight, depth, primid: a colour straight from the camera hit. One loop per mode,
/// so the per-pixel loop has no mode switch.
template <Shading kShading>
void shade_primary(const Frame& f, const TilePixels& tile, TileScratch& s) noexcept {
    for (uint32_t i = 0; i < tile.pixel_count(); ++i) {
        const Hit& hit = s.hits[i];
        if (!hit.is_hit()) {
            add_background(f, s.sum[i]);
            continue;
        }
        if constexpr (kShading == Shading::kNormals) {
            const Vec3 n = display_normal(f.tris[hit.prim], direction(s.rays[i]));
            add(s.sum[i], 0.5f * n.x + 0.5f, 0.5f * n.y + 0.5f, 0.5f * n.z + 0.5f, 1.0f);
        } else if constexpr (kShading == Shading::kEyelight) {
            const Vec3 d = direction(s.rays[i]);
            // Camera directions are unit vectors; the clamp only absorbs rounding.
            const float c = std::min(1.0f, std::fabs(dot(display_normal(f.tris[hit.prim], d), d)));
            add(s.sum[i], c, c, c, 1.0f);
        } else if constexpr (kShading == Shading::kDepth) {
            add(s.sum[i], hit.t, hit.t, hit.t, 1.0f);
        } else {
            static_assert(kShading == Shading::kPrimId);
            const auto c = prim_colour(hit.prim);
            add(s.sum[i], c[0], c[1], c[2], 1.0f);
        }
    }
}

/// Collects the camera hits of the tile as surfaces (misses get the background). Returns the
/// number of hits.
uint32_t gather_surfaces(const Frame& f, const TilePixels& tile, TileScratch& s) noexcept {
    uint32_t count = 0;
    for (uint32_t i = 0; i < tile.pixel_count(); ++i) {
        if (!s.hits[i].is_hit()) {
            add_background(f, s.sum[i]);
            continue;
        }
        s.surfaces[count] = surface_at(f.tris, s.rays[i], s.hits[i], f.offset);
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
            PixelRng rng(f.settings.seed, tile.px(i), tile.py(i), sample, Stream::kAo, j);
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
        float tmax = kInf;
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
            PixelRng rng(f.settings.seed, tile.px(i), tile.py(i), sample, Stream::kBounce, bounce);
            float throughput = s.throughput[p] * f.settings.albedo;
            if (bounce >= kRouletteStartBounce) {
                const float survival = std::min(throughput, kMaxSurvival);
                if (!(rng.uniform() < survival)) continue;
                throughput /= survival;
            }
            if (!(throughput > 0.0f)) continue;
            const Surface& surface = s.surfaces[p];
            const Vec3 d = cosine_direction(surface.normal, rng);
            s.rays[count] = Ray{
                surface.origin.x, surface.origin.y, surface.origin.z, 0.0f, d.x, d.y, d.z, kInf};
            s.ray_path[count] = static_cast<uint16_t>(p);
            s.ray_weight[count] = throughput;
            ++count;
        }
        if (count == 0) break;
        tracer.intersect(std::span<const Ray>(s.rays.data(), count),
                         std::span<Hit>(s.hits.data(), count));
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
            s.surfaces[live] = surface_at(f.tris, s.rays[r], s.hits[r], f.offset);
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
        tracer.intersect(std::span<const Ray>(s.rays.data(), n), std::span<Hit>(s.hits.data(), n));
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
Image render_frame(const KdTree& tree, const RenderSettings& settings, const Tracer& tracer,
                   const RenderControl& control, RenderStats* stats) {
    const auto start = Clock::now();
    const Frame frame = make_frame(tree, settings);
    Image image;
    image.width = frame.region.width;
    image.height = frame.region.height;
    image.channels = frame.channels;
    image.pixels.resize(size_t{image.width} * image.height * image.channels);

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

void validate_render_settings(const RenderSettings& s) {
    require_range("width", s.width, 1, kMaxImageSize);
    require_range("height", s.height, 1, kMaxImageSize);
    if (s.region) {
        const PixelRegion& r = *s.region;
        if (r.width == 0 || r.height == 0) {
            fail("region width and height must be at least 1 (got " + std::to_string(r.width) +
                 " x " + std::to_string(r.height) + ")");
        }
        // 64-bit sums: x + width cannot wrap.
        if (uint64_t{r.x} + r.width > s.width || uint64_t{r.y} + r.height > s.height) {
            fail("region (x " + std::to_string(r.x) + ", y " + std::to_string(r.y) + ", width " +
                 std::to_string(r.width) + ", height " + std::to_string(r.height) +
                 ") is not inside the " + std::to_string(s.width) + " x " +
                 std::to_string(s.height) + " frame");
        }
    }
    require_range("spp", s.spp, 1, kMaxSamplesPerPixel);
    if (!parse_shading(shading_name(s.shading))) {
        fail("shading " + std::to_string(static_cast<uint32_t>(s.shading)) +
             " is not a known mode");
    }
    require_range("ao_samples", s.ao_samples, 1, kMaxAoSamples);
    if (!(s.ao_distance > 0.0f) || !std::isfinite(s.ao_distance)) {
        fail("ao_distance " + format_float(s.ao_distance) + " must be a finite value > 0");
    }
    if (!(s.albedo >= 0.0f && s.albedo <= 1.0f))
        fail("albedo " + format_float(s.albedo) + " must be in [0, 1]");
    require_range("bounces", s.bounces, 0, kMaxBounces);
    require_finite_nonnegative("sky", s.sky);
    if (!is_finite(s.background))
        fail("background " + format_vec(s.background) + " has a NaN or infinite component");
    if (s.tile_size != 8 && s.tile_size != 16) {
        fail("tile_size " + std::to_string(s.tile_size) + " must be 8 or 16");
    }
    const Light& light = s.light;
    require_finite_nonnegative("light.intensity", light.intensity);
    switch (light.kind) {
        case LightKind::kDirectional: {
            const Vec3 d = light.direction;
            if (!is_finite(d) || dot(d, d) == 0.0f || !std::isfinite(dot(d, d))) {
                fail("light.direction " + format_vec(d) +
                     " must be finite, non-zero and not too long");
            }
            break;
        }
        case LightKind::kPoint:
            if (!is_finite(light.position)) {
                fail("light.position " + format_vec(light.position) +
                     " has a NaN or infinite component");
            }
            break;
        default:
            fail("light.kind " + std::to_string(static_cast<uint32_t>(light.kind)) +
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

Image render(const KdTree& tree, const RenderSettings& settings, const RenderControl& control,
             RenderStats* stats) {
    return render_frame(tree, settings, TreeTracer{tree}, control, stats);
}

std::vector<Ray> render_camera_rays(const KdTree& tree, const RenderSettings& settings,
                                    uint32_t sample) {
    const Frame frame = make_frame(tree, settings);
    if (sample >= settings.spp) {
        fail("camera ray sample " + std::to_string(sample) + " must be below spp " +
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
    return render_frame(tree, settings, FunctionTracer{trace}, control, stats);
}

}  // namespace detail
}  // namespace kdrt
