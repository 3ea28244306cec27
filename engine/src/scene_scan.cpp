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
    out.geom.resize(all.hits.size());
    // The returns in beam order, each beam's hits from its place in the traced order.
    detail::lidar_points(
        std::span<const uint32_t>(order), std::span<const uint64_t>(all.offsets),
        std::span<const SceneHit>(all.hits), channels,
        [&](const SceneHit& hit) { return hit_point(scene, hit); },
        [&](uint64_t at, const SceneHit& hit) { out.geom[at] = hit.geom; }, cloud);
    return out;
}

}  // namespace kdrt
