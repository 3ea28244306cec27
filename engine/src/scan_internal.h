#pragma once
// Internal: the rays of the sensor scans, shared by the mesh scans (scan.cpp) and the scene scans
// (scene_scan.cpp), so both trace exactly the same rays and compute depth the same way.

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

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

/// The order in which a scene's lidar beams are traced: tiles of kTileAzimuth azimuth steps by
/// kTileChannels channels (a closest-hit packet's eight beams at one elevation, side by side),
/// in blocks of kBlockAzimuth steps by kBlockChannels channels, each block's tiles azimuth-major.
/// order[k] is the azimuth-major index (lidar_rays) of the k-th beam traced; every beam once.
/// The beams of a column of blocks (azimuth steps [a, a + kBlockAzimuth), every channel) are the
/// same in both orders, at the same places. Parallel over the arena.
inline constexpr uint32_t kTileAzimuth = 8, kTileChannels = 1;
inline constexpr uint32_t kBlockAzimuth = 64, kBlockChannels = 16;
[[nodiscard]] std::vector<uint32_t> lidar_tile_order(uint32_t channels, uint32_t azimuth_steps);

/// The beams of a lidar scan (`spec` validated) in the order `order` (azimuth-major indices):
/// ray k is lidar_rays(spec)[order[k]], bit for bit. Parallel over the arena.
[[nodiscard]] std::vector<Ray> lidar_rays(const LidarSpec& spec, std::span<const uint32_t> order);

/// The cloud of a lidar scan from its every-hit answer in CSR form (`offsets`, one entry per beam
/// and one more; `hits`, each with t and prim), the point of a hit from point_of(hit): the
/// returns of beam b are its hits in order, channel b % channels, azimuth step b / channels.
/// Parallel over the arena.
template <class HitT, class PointOf>
void lidar_points(std::span<const uint64_t> offsets, std::span<const HitT> hits, uint32_t channels,
                  PointOf&& point_of, PointCloud& cloud) {
    cloud.points.resize(hits.size());
    const size_t beams = offsets.size() - 1;
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, beams, 1024), [&](const tbb::blocked_range<size_t>& r) {
            for (size_t b = r.begin(); b != r.end(); ++b) {
                for (uint64_t k = offsets[b]; k < offsets[b + 1]; ++k) {
                    const HitT& hit = hits[k];
                    const Vec3 p = point_of(hit);
                    cloud.points[k] = LidarPoint{p.x,
                                                 p.y,
                                                 p.z,
                                                 hit.t,
                                                 static_cast<uint32_t>(b % channels),
                                                 static_cast<uint32_t>(b / channels),
                                                 static_cast<uint32_t>(k - offsets[b]),
                                                 hit.prim};
                }
            }
        });
}

}  // namespace kdrt::detail
