#pragma once
/// Deterministic ray sets for benchmarks and tests (kdrt-bench rays, kdrt rays).

#include <cstdint>
#include <optional>
#include <string_view>
#include <vector>

#include "kdrt/camera.h"
#include "kdrt/kdtree.h"
#include "kdrt/types.h"

namespace kdrt {

enum class RayKind : uint32_t {
    kPrimary = 0,  ///< res x res camera rays through pixel centres (RayGenOptions::camera)
    kShadow = 1,   ///< from each primary hit point towards a point light (occlusion query)
    kDiffuse = 2,  ///< from each primary hit point, cosine-weighted into the visible hemisphere
    kRandom = 3,  ///< res x res rays, origin uniform in the bounds, direction uniform on the sphere
};

[[nodiscard]] std::optional<RayKind> parse_ray_kind(std::string_view name) noexcept;
[[nodiscard]] std::string_view ray_kind_name(RayKind kind) noexcept;

struct RayGenOptions {
    RayKind kind = RayKind::kPrimary;
    uint32_t res = 1024;
    uint64_t seed = 1;
    /// The camera of the primary rays, and so of the shadow and diffuse sets built from their
    /// hits (a square image). Default: default_camera of the tree's bounds. Ignored by kRandom.
    std::optional<CameraSpec> camera = std::nullopt;
};

/// Generates a ray set for the tree's mesh. Shadow and diffuse sets trace the primary rays first
/// and have one ray per primary hit. The same inputs give the same rays on every machine and
/// thread count. Shadow rays are occlusion queries (the caller sets the KDRR flag).
[[nodiscard]] std::vector<Ray> generate_rays(const KdTree& tree, const RayGenOptions& options);

}  // namespace kdrt
