#include "kdrt/raygen.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "geometry.h"
#include "kdrt/camera.h"
#include "kdrt/trace.h"
#include "random.h"
#include "sampling.h"

namespace kdrt {
namespace {

using detail::cosine_direction;
using detail::CounterRng;
using detail::diagonal;
using detail::normalized;
using detail::NormalScaling;
using detail::ray_set_rng;
using detail::scene_box;
using detail::sphere_direction;
using detail::Surface;
using detail::surface_at;
using detail::surface_offset;

constexpr float kInf = std::numeric_limits<float>::infinity();

// Largest res: res * res rays must fit the u32 count of a KDRR batch.
constexpr uint32_t kMaxRes = 65535;

// Grain of the parallel loops: big enough that task overhead is noise, small enough to balance.
constexpr size_t kGrain = 4096;

template <typename Body>
void parallel_indices(size_t count, Body body) {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, count, kGrain),
                      [&](const tbb::blocked_range<size_t>& range) {
                          for (size_t i = range.begin(); i != range.end(); ++i) body(i);
                      });
}

std::vector<Ray> primary_rays(const KdTree& tree, uint32_t res,
                              const std::optional<CameraSpec>& spec) {
    const Camera camera(spec ? *spec : default_camera(scene_box(tree.bounds), 1.0f), res, res);
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
    const float offset = surface_offset(scene_box(tree.bounds));
    std::vector<Ray> rays(hit_pixels.size());
    parallel_indices(rays.size(), [&](size_t i) {
        const uint32_t pixel = hit_pixels[i];
        rays[i] =
            make(pixel, surface_at<NormalScaling::kDivision>(tree.triangle(hits[pixel].prim),
                                                             primary[pixel], hits[pixel], offset));
    });
    return rays;
}

std::vector<Ray> shadow_rays(const KdTree& tree, uint32_t res,
                             const std::optional<CameraSpec>& camera) {
    // A point light above, in front of and to the right of the scene, 1.5 box diagonals from its
    // centre: outside the box, so every shadow segment ends in empty space. (A box with a zero
    // diagonal holds only zero-area triangles, which are never hit, so there are no shadow rays.)
    const Aabb box = scene_box(tree.bounds);
    const Vec3 centre = (box.lo + box.hi) * 0.5f;
    const float diag = diagonal(box);
    const Vec3 light = centre + normalized(Vec3{0.6f, 1.0f, 0.8f}) * (1.5f * diag);
    return secondary_rays(tree, res, camera, [&](uint32_t, const Surface& s) {
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
    return secondary_rays(tree, res, camera, [&](uint32_t pixel, const Surface& s) {
        CounterRng rng = ray_set_rng(seed, RayKind::kDiffuse, pixel);
        const Vec3 dir = cosine_direction(s.normal, rng);
        return Ray{s.origin.x, s.origin.y, s.origin.z, 0.0f, dir.x, dir.y, dir.z, kInf};
    });
}

std::vector<Ray> random_rays(const KdTree& tree, uint32_t res, uint64_t seed) {
    const Aabb box = scene_box(tree.bounds);
    const Vec3 ext = box.extent();
    std::vector<Ray> rays(size_t{res} * res);
    parallel_indices(rays.size(), [&](size_t i) {
        CounterRng rng = ray_set_rng(seed, RayKind::kRandom, i);
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
