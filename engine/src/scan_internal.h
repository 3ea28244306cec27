#pragma once
// Internal: the rays of the sensor scans, shared by the mesh scans (scan.cpp) and the scene scans
// (scene_scan.cpp), so both trace exactly the same rays and compute depth the same way.

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "kdrt/scan.h"
#include "kdrt/trace.h"

namespace kdrt::detail {

/// The rays of a pinhole scan (`spec` validated) in pixel order, and for DepthKind::kDepth each
/// pixel's cosine to the optical axis (else `cosines` is left empty). Parallel over the arena.
void pinhole_rays(const PinholeSpec& spec, std::vector<Ray>& rays, std::vector<double>& cosines);

/// The depth image value of a hit at `t` of pixel `p`: t for kRange, t * cos in double for kDepth.
inline float pinhole_depth(float t, const std::vector<double>& cosines, size_t p) noexcept {
    return cosines.empty() ? t : static_cast<float>(static_cast<double>(t) * cosines[p]);
}

/// The beams of a lidar scan (`spec` validated), azimuth-major: lidar_rays(spec, order) with
/// every beam in that order. Parallel over the arena.
[[nodiscard]] std::vector<Ray> lidar_rays(const LidarSpec& spec);

/// The order in which the lidar beams (mesh and scene scans) are traced: tiles of kTileAzimuth
/// azimuth steps by kTileChannels channels (a closest-hit packet's eight beams at one elevation,
/// side by side), in blocks of kBlockAzimuth steps by kBlockChannels channels, each block's tiles
/// azimuth-major. order[k] is the azimuth-major index (lidar_rays) of the k-th beam traced; every
/// beam once. The beams of a column of blocks (azimuth steps [a, a + kBlockAzimuth), every channel)
/// are the same in both orders, at the same places. Parallel over the arena.
inline constexpr uint32_t kTileAzimuth = 8, kTileChannels = 1;
inline constexpr uint32_t kBlockAzimuth = 64, kBlockChannels = 16;
[[nodiscard]] std::vector<uint32_t> lidar_tile_order(uint32_t channels, uint32_t azimuth_steps);

/// The beams of a lidar scan (`spec` validated) in the order `order` (azimuth-major indices):
/// ray k is lidar_rays(spec)[order[k]], bit for bit. Parallel over the arena.
[[nodiscard]] std::vector<Ray> lidar_rays(const LidarSpec& spec, std::span<const uint32_t> order);

/// The cloud of a lidar scan from its every-hit answer in CSR form for beams traced in the order
/// `order` (lidar_tile_order): `offsets`, one entry per traced beam and one more; `hits`, each
/// with t and prim; the returns of the k-th beam traced, beam b = order[k], are its hits in order,
/// channel b % channels, azimuth step b / channels. Writes cloud.points in beam order
/// (azimuth-major, then return), the point of a hit from point_of(hit), and calls
/// each_point(at, hit) for the point at cloud.points[at]. The mesh and the scene lidar scans both
/// write their clouds here. A column of blocks holds the same beams and returns in both orders
/// (lidar_tile_order): in parallel by column over the arena.
template <class HitT, class PointOf, class EachPoint>
void lidar_points(std::span<const uint32_t> order, std::span<const uint64_t> offsets,
                  std::span<const HitT> hits, uint32_t channels, PointOf&& point_of,
                  EachPoint&& each_point, PointCloud& cloud) {
    cloud.points.resize(hits.size());
    const size_t beams = order.size();
    const size_t column = size_t{kBlockAzimuth} * channels;
    tbb::parallel_for(tbb::blocked_range<size_t>(0, (beams + column - 1) / column, 1),
                      [&](const tbb::blocked_range<size_t>& r) {
                          std::vector<uint64_t> start;
                          for (size_t col = r.begin(); col != r.end(); ++col) {
                              const size_t k0 = col * column, k1 = std::min(beams, k0 + column);
                              // start[b - k0]: where beam b's returns go, from the column's first
                              // return.
                              start.assign(k1 - k0 + 1, 0);
                              for (size_t k = k0; k < k1; ++k)
                                  start[order[k] - k0 + 1] = offsets[k + 1] - offsets[k];
                              start[0] = offsets[k0];
                              for (size_t i = 0; i < k1 - k0; ++i) start[i + 1] += start[i];
                              for (size_t k = k0; k < k1; ++k) {
                                  const uint32_t b = order[k];
                                  for (uint64_t j = offsets[k]; j < offsets[k + 1]; ++j) {
                                      const HitT& hit = hits[j];
                                      const Vec3 p = point_of(hit);
                                      const uint64_t at = start[b - k0] + (j - offsets[k]);
                                      cloud.points[at] =
                                          LidarPoint{p.x,
                                                     p.y,
                                                     p.z,
                                                     hit.t,
                                                     b % channels,
                                                     b / channels,
                                                     static_cast<uint32_t>(j - offsets[k]),
                                                     hit.prim};
                                      each_point(at, hit);
                                  }
                              }
                          }
                      });
}

/// The mesh lidar scan (scan_lidar(tree, spec)) with its every-hit query traced by `isa`
/// (default: default_isa()), so that tests can run it on every ISA.
[[nodiscard]] PointCloud scan_lidar(const KdTree& tree, const LidarSpec& spec,
                                    std::optional<Isa> isa);

}  // namespace kdrt::detail
