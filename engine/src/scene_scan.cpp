// Scene scans: the mesh scans' rays (scan_internal.h), traced through the scene's closest hit
// and every-hit queries, with the geometry id beside each answer.

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "kdrt/scene.h"
#include "scan_internal.h"
#include "scene_internal.h"

namespace kdrt {

SceneDepthImage scan_pinhole(const Scene& scene, const PinholeSpec& spec) {
    validate(spec);
    SceneDepthImage out;
    DepthImage& image = out.image;
    image.width = spec.intrinsics.width;
    image.height = spec.intrinsics.height;
    image.kind = spec.kind;
    std::vector<Ray> rays;
    std::vector<double> cosines;
    detail::pinhole_rays(spec, rays, cosines);
    const size_t n = rays.size();
    std::vector<SceneHit> hits(n);
    intersect(scene, rays, hits);
    image.depth.resize(n);
    image.prim.resize(n);
    out.geom.resize(n);
    if (spec.normals) image.normals.resize(n);
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, n, 4096), [&](const tbb::blocked_range<size_t>& r) {
            for (size_t p = r.begin(); p != r.end(); ++p) {
                const SceneHit& hit = hits[p];
                image.depth[p] = hit.is_hit() ? detail::pinhole_depth(hit.t, cosines, p)
                                              : std::numeric_limits<float>::infinity();
                image.prim[p] = hit.prim;
                out.geom[p] = hit.geom;
                if (spec.normals) image.normals[p] = hit_normal(scene, hit);  // zero on a miss
            }
        });
    return out;
}

ScenePointCloud scan_lidar(const Scene& scene, const LidarSpec& spec) {
    validate(spec);
    const auto channels = static_cast<uint32_t>(spec.elevation_deg.size());
    // The beams in tiles (scan_internal.h), so that the rays reaching one instance in a round go
    // to the mesh's packets eight at one elevation, side by side: fewer triangle tests than eight
    // channels of one azimuth (the answers are per beam, so they do not depend on the order).
    const std::vector<uint32_t> order = detail::lidar_tile_order(channels, spec.azimuth_steps);
    const std::vector<Ray> rays = detail::lidar_rays(spec, order);
    // The nearest `returns` hits of each beam, as intersect_all (merge_coincident) keeps them,
    // without tracing the instances beyond them.
    const SceneAllHits all = detail::nearest_hits(scene, rays, spec.returns, true);
    ScenePointCloud out;
    PointCloud& cloud = out.cloud;
    cloud.channels = channels;
    cloud.azimuth_steps = spec.azimuth_steps;
    cloud.returns = spec.returns;
    // The returns in beam order (azimuth-major, as lidar_points writes them), each beam's hits
    // from its place in the traced order. A column of blocks holds the same beams and returns in
    // both orders (scan_internal.h): in parallel by column.
    const size_t beams = order.size();
    cloud.points.resize(all.hits.size());
    out.geom.resize(all.hits.size());
    const size_t column = size_t{detail::kBlockAzimuth} * channels;
    tbb::parallel_for(tbb::blocked_range<size_t>(0, (beams + column - 1) / column, 1),
                      [&](const tbb::blocked_range<size_t>& r) {
                          std::vector<uint64_t> start;
                          for (size_t col = r.begin(); col != r.end(); ++col) {
                              const size_t k0 = col * column, k1 = std::min(beams, k0 + column);
                              // start[b - k0]: where beam b's returns go, from the column's first
                              // return.
                              start.assign(k1 - k0 + 1, 0);
                              for (size_t k = k0; k < k1; ++k)
                                  start[order[k] - k0 + 1] = all.offsets[k + 1] - all.offsets[k];
                              start[0] = all.offsets[k0];
                              for (size_t i = 0; i < k1 - k0; ++i) start[i + 1] += start[i];
                              for (size_t k = k0; k < k1; ++k) {
                                  const uint32_t b = order[k];
                                  for (uint64_t j = all.offsets[k]; j < all.offsets[k + 1]; ++j) {
                                      const SceneHit& hit = all.hits[j];
                                      const Vec3 p = hit_point(scene, hit);
                                      const uint64_t at = start[b - k0] + (j - all.offsets[k]);
                                      cloud.points[at] =
                                          LidarPoint{p.x,
                                                     p.y,
                                                     p.z,
                                                     hit.t,
                                                     b % channels,
                                                     b / channels,
                                                     static_cast<uint32_t>(j - all.offsets[k]),
                                                     hit.prim};
                                      out.geom[at] = hit.geom;
                                  }
                              }
                          }
                      });
    return out;
}

}  // namespace kdrt
