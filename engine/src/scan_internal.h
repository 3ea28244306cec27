#pragma once
// Internal: the rays of the sensor scans, shared by the mesh scans (scan.cpp) and the scene scans
// (scene_scan.cpp), so both trace exactly the same rays and compute depth the same way.

#include <cstddef>
#include <vector>

#include "kdrt/scan.h"

namespace kdrt::detail {

/// The rays of a pinhole scan (`spec` validated) in pixel order, and for DepthKind::kDepth each
/// pixel's cosine to the optical axis (else `cosines` is left empty). Parallel over the arena.
void pinhole_rays(const PinholeSpec& spec, std::vector<Ray>& rays, std::vector<double>& cosines);

/// The depth image value of a hit at `t` of pixel `p`: t for kRange, t * cos in double for kDepth.
inline float pinhole_depth(float t, const std::vector<double>& cosines, size_t p) noexcept {
    return cosines.empty() ? t : static_cast<float>(static_cast<double>(t) * cosines[p]);
}

/// The beams of a lidar scan (`spec` validated), azimuth-major. Parallel over the arena.
[[nodiscard]] std::vector<Ray> lidar_rays(const LidarSpec& spec);

}  // namespace kdrt::detail
