#include "kdrt/raygen.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "kdrt/camera.h"
#include "kdrt/trace.h"
#include "sampling.h"

namespace kdrt {
namespace {

using detail::cosine_direction;
using detail::is_finite;
using detail::normalized;

constexpr float kInf = std::numeric_limits<float>::infinity();

// Largest res: res * res rays must fit the u32 count of a KDRR batch.
constexpr uint32_t kMaxRes = 65535;

// Grain of the parallel loops: big enough that task overhead is noise, small enough to balance.
constexpr size_t kGrain = 4096;

// splitmix64 finaliser (Steele, Lea & Flood 2014): a bijection on 64 bits with good avalanche.
constexpr uint64_t mix64(uint64_t x) noexcept {
    x += 0x9E3779B97F4A7C15ull;
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
    return x ^ (x >> 31);
}

/// Counter-based random numbers: the stream of a ray depends only on (seed, kind, ray index), never
/// on which thread generates it or in which order, so a ray set is the same at any thread count.
class CounterRng {
public:
    CounterRng(uint64_t seed, RayKind kind, uint64_t index) noexcept
        : state_(mix64(mix64(seed ^ (static_cast<uint64_t>(kind) << 56)) ^ index)) {}

    /// Uniform in [0, 1): 24 random bits, so every value is an exact float.
    float uniform() noexcept {
        state_ += 0x9E3779B97F4A7C15ull;
        return static_cast<float>(mix64(state_) >> 40) * 0x1.0p-24f;
    }
    /// Uniform in [-1, 1).
    float symmetric() noexcept { return 2.0f * uniform() - 1.0f; }

private:
    uint64_t state_;
};

/// The box the ray sets are placed in: the tree bounds, or the unit cube around the origin for an
/// empty tree (the same fallback default_camera uses).
Aabb scene_box(const KdTree& tree) noexcept {
    if (!tree.bounds.empty() && is_finite(tree.bounds.lo) && is_finite(tree.bounds.hi)) {
        return tree.bounds;
    }
    return Aabb{{-0.5f, -0.5f, -0.5f}, {0.5f, 0.5f, 0.5f}};
}

/// Distance a secondary ray's origin is pushed off the surface. Relative to the scene size and to
/// the magnitude of the coordinates (far from the origin a float has fewer bits below the point):
/// about 100 ulps of the largest coordinate, far below the size of any visible triangle.
float surface_offset(const Aabb& box) noexcept {
    const Vec3 ext = box.extent();
    const float diag = std::sqrt(dot(ext, ext));
    float magnitude = 0.0f;
    for (int a = 0; a < 3; ++a) {
        magnitude = std::max({magnitude, std::fabs(box.lo[a]), std::fabs(box.hi[a])});
    }
    return 1e-5f * (diag + magnitude);
}

/// A primary hit, prepared for spawning a secondary ray.
struct SurfacePoint {
    Vec3 origin;  ///< the hit point, offset along `normal`
    Vec3 normal;  ///< unit geometric normal on the side the primary ray came from
};

SurfacePoint surface_point(const KdTree& tree, const Ray& ray, const Hit& hit,
                           float offset) noexcept {
    const TriVerts& tri = tree.tris[hit.prim];
    const Vec3 v0{tri.v0[0], tri.v0[1], tri.v0[2]};
    const Vec3 v1{tri.v1[0], tri.v1[1], tri.v1[2]};
    const Vec3 v2{tri.v2[0], tri.v2[1], tri.v2[2]};
    // The barycentric point lies on the triangle to rounding; o + t*d can be off by |t*d| ulps.
    const Vec3 p = v0 * (1.0f - hit.u - hit.v) + v1 * hit.u + v2 * hit.v;
    // Cross product in double: sliver triangles would lose most bits of their normal in float.
    const double e1[3] = {double{v1.x} - v0.x, double{v1.y} - v0.y, double{v1.z} - v0.z};
    const double e2[3] = {double{v2.x} - v0.x, double{v2.y} - v0.y, double{v2.z} - v0.z};
    const double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                         e1[0] * e2[1] - e1[1] * e2[0]};
    const double n_len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    const Vec3 dir{ray.dx, ray.dy, ray.dz};
    Vec3 normal;
    if (n_len > 0.0 && std::isfinite(n_len)) {
        normal = {static_cast<float>(n[0] / n_len), static_cast<float>(n[1] / n_len),
                  static_cast<float>(n[2] / n_len)};
        if (dot(normal, dir) > 0.0f) normal = normal * -1.0f;
    } else {
        // The engine never reports a hit on a zero-area triangle; stay well defined regardless.
        normal = normalized(dir) * -1.0f;
    }
    return {p + normal * offset, normal};
}

/// Direction uniform on the unit sphere: a uniform point in the unit ball, normalised.
Vec3 sphere_direction(CounterRng& rng) noexcept {
    Vec3 v;
    float len2;
    do {
        v = {rng.symmetric(), rng.symmetric(), rng.symmetric()};
        len2 = dot(v, v);
    } while (len2 > 1.0f || len2 < 1e-4f);
    return v * (1.0f / std::sqrt(len2));
}

template <typename Body>
void parallel_indices(size_t count, Body body) {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, count, kGrain),
                      [&](const tbb::blocked_range<size_t>& range) {
                          for (size_t i = range.begin(); i != range.end(); ++i) body(i);
                      });
}

std::vector<Ray> primary_rays(const KdTree& tree, uint32_t res,
                              const std::optional<CameraSpec>& spec) {
    const Camera camera(spec ? *spec : default_camera(scene_box(tree), 1.0f), res, res);
    std::vector<Ray> rays(size_t{res} * res);
    parallel_indices(rays.size(), [&](size_t i) {
        const auto x = static_cast<uint32_t>(i % res);
        const auto y = static_cast<uint32_t>(i / res);
        rays[i] = camera.ray(static_cast<float>(x) + 0.5f, static_cast<float>(y) + 0.5f);
    });
    return rays;
}

/// One secondary ray per primary hit, in pixel order; `make(i, point, primary)` builds ray i.
template <typename Make>
std::vector<Ray> secondary_rays(const KdTree& tree, uint32_t res,
                                const std::optional<CameraSpec>& camera, Make make) {
    const std::vector<Ray> primary = primary_rays(tree, res, camera);
    std::vector<Hit> hits(primary.size());
    intersect_single(tree, primary, hits);
    std::vector<uint32_t> hit_pixels;
    for (size_t i = 0; i < hits.size(); ++i) {
        if (hits[i].is_hit()) hit_pixels.push_back(static_cast<uint32_t>(i));
    }
    const float offset = surface_offset(scene_box(tree));
    std::vector<Ray> rays(hit_pixels.size());
    parallel_indices(rays.size(), [&](size_t i) {
        const uint32_t pixel = hit_pixels[i];
        rays[i] = make(pixel, surface_point(tree, primary[pixel], hits[pixel], offset));
    });
    return rays;
}

std::vector<Ray> shadow_rays(const KdTree& tree, uint32_t res,
                             const std::optional<CameraSpec>& camera) {
    // A point light above, in front of and to the right of the scene, 1.5 box diagonals from its
    // centre: outside the box, so every shadow segment ends in empty space. (A box with a zero
    // diagonal holds only zero-area triangles, which are never hit, so there are no shadow rays.)
    const Aabb box = scene_box(tree);
    const Vec3 ext = box.extent();
    const Vec3 centre = (box.lo + box.hi) * 0.5f;
    const float diag = std::sqrt(dot(ext, ext));
    const Vec3 light = centre + normalized(Vec3{0.6f, 1.0f, 0.8f}) * (1.5f * diag);
    return secondary_rays(tree, res, camera, [&](uint32_t, const SurfacePoint& s) {
        const Vec3 to_light = light - s.origin;
        const float distance = std::sqrt(dot(to_light, to_light));
        const Vec3 dir = to_light * (1.0f / distance);
        // Stop short of the light by a relative 1e-3: the segment ends strictly before it.
        return Ray{s.origin.x, s.origin.y, s.origin.z, 0.0f,
                   dir.x,      dir.y,      dir.z,      distance * 0.999f};
    });
}

std::vector<Ray> diffuse_rays(const KdTree& tree, uint32_t res, uint64_t seed,
                              const std::optional<CameraSpec>& camera) {
    return secondary_rays(tree, res, camera, [&](uint32_t pixel, const SurfacePoint& s) {
        CounterRng rng(seed, RayKind::kDiffuse, pixel);
        const Vec3 dir = cosine_direction(s.normal, rng);
        return Ray{s.origin.x, s.origin.y, s.origin.z, 0.0f, dir.x, dir.y, dir.z, kInf};
    });
}

std::vector<Ray> random_rays(const KdTree& tree, uint32_t res, uint64_t seed) {
    const Aabb box = scene_box(tree);
    const Vec3 ext = box.extent();
    std::vector<Ray> rays(size_t{res} * res);
    parallel_indices(rays.size(), [&](size_t i) {
        CounterRng rng(seed, RayKind::kRandom, i);
        Vec3 o;
        for (int a = 0; a < 3; ++a) {
            // lo + u * extent can round up past hi for u just below 1: clamp.
            o[a] = std::min(box.lo[a] + rng.uniform() * ext[a], box.hi[a]);
        }
        const Vec3 dir = sphere_direction(rng);
        rays[i] = Ray{o.x, o.y, o.z, 0.0f, dir.x, dir.y, dir.z, kInf};
    });
    return rays;
}

}  // namespace

std::optional<RayKind> parse_ray_kind(std::string_view name) noexcept {
    if (name == "primary") return RayKind::kPrimary;
    if (name == "shadow") return RayKind::kShadow;
    if (name == "diffuse") return RayKind::kDiffuse;
    if (name == "random") return RayKind::kRandom;
    return std::nullopt;
}

std::string_view ray_kind_name(RayKind kind) noexcept {
    switch (kind) {
        case RayKind::kPrimary:
            return "primary";
        case RayKind::kShadow:
            return "shadow";
        case RayKind::kDiffuse:
            return "diffuse";
        case RayKind::kRandom:
            return "random";
    }
    return "unknown";
}

std::vector<Ray> generate_rays(const KdTree& tree, const RayGenOptions& options) {
    if (options.res > kMaxRes) {
        throw std::invalid_argument("ray generation: res " + std::to_string(options.res) +
                                    " is too large (at most " + std::to_string(kMaxRes) +
                                    ", so res * res rays fit a 32-bit count)");
    }
    if (options.res == 0) return {};
    switch (options.kind) {
        case RayKind::kPrimary:
            return primary_rays(tree, options.res, options.camera);
        case RayKind::kShadow:
            return shadow_rays(tree, options.res, options.camera);
        case RayKind::kDiffuse:
            return diffuse_rays(tree, options.res, options.seed, options.camera);
        case RayKind::kRandom:
            return random_rays(tree, options.res, options.seed);
    }
    throw std::invalid_argument("ray generation: unknown ray kind " +
                                std::to_string(static_cast<uint32_t>(options.kind)));
}

}  // namespace kdrt
