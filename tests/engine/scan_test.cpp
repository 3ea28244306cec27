// Sensor scans (kdrt/scan.h): every pixel and every lidar beam equals the brute-force trace of the
// ray built here from the documented conventions; depth and range agree; a beam through a shared
// edge gives one return; the answers are the same bytes at 1 and 2 threads; every validation
// error names its field.

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <numbers>

#include <tbb/task_arena.h>

#include "kdrt/camera.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/query.h"
#include "kdrt/scan.h"
#include "kdrt/trace.h"
#include "oracle.h"
#include "scan_internal.h"
#include "scenes.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

Mesh load_data_mesh(const char* name) {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/" + name);
    if (!mesh) throw std::runtime_error(mesh.error().to_string());
    return std::move(mesh).value();
}

bool same_float(float a, float b) { return std::memcmp(&a, &b, 4) == 0; }

/// A camera-to-world pose looking from `eye` towards `target` (OpenCV axes: z forward, y down),
/// with world +y as "up" (so the camera's +y is world -y-ish).
Pose look_pose(const double eye[3], const double target[3]) {
    double z[3] = {target[0] - eye[0], target[1] - eye[1], target[2] - eye[2]};
    double l = std::sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2]);
    for (double& c : z) c /= l;
    const double up[3] = {0, 1, 0};
    double x[3] = {z[1] * up[2] - z[2] * up[1], z[2] * up[0] - z[0] * up[2],
                   z[0] * up[1] - z[1] * up[0]};  // z x up = right
    l = std::sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]);
    for (double& c : x) c /= l;
    const double y[3] = {z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2],
                         z[0] * x[1] - z[1] * x[0]};  // z x x = down
    Pose p;
    for (int r = 0; r < 3; ++r) {
        p.m[4 * r] = x[r];
        p.m[4 * r + 1] = y[r];
        p.m[4 * r + 2] = z[r];
        p.m[4 * r + 3] = eye[r];
    }
    return p;
}

/// The ray of sensor-frame direction v from the pose, as scan.h documents it (built here, not
/// with the engine's helpers).
Ray documented_ray(const Pose& pose, const double v[3], float tmin, float tmax) {
    const double len = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    float d[3];
    for (int r = 0; r < 3; ++r) {
        const double* row = &pose.m[4 * r];
        d[r] = static_cast<float>((row[0] * v[0] + row[1] * v[1] + row[2] * v[2]) / len);
    }
    return Ray{static_cast<float>(pose.m[3]),
               static_cast<float>(pose.m[7]),
               static_cast<float>(pose.m[11]),
               tmin,
               d[0],
               d[1],
               d[2],
               tmax};
}

struct BunnyScene {
    Mesh mesh = load_data_mesh("bunny00.off");
    KdTree tree = build_kdtree(mesh);
    std::vector<TriVerts> tris = triangles_by_id(tree);
    double centre[3], radius;
    BunnyScene() {
        const Vec3 e = tree.bounds.extent();
        radius = 0.5 * std::sqrt(dot(e, e));
        for (int a = 0; a < 3; ++a)
            centre[a] = 0.5 * (double{tree.bounds.lo[a]} + double{tree.bounds.hi[a]});
    }
};

PinholeSpec bunny_camera(const BunnyScene& s, uint32_t w, uint32_t h) {
    const double eye[3] = {s.centre[0] + 0.7 * s.radius, s.centre[1] + 0.4 * s.radius,
                           s.centre[2] + 2.2 * s.radius};
    PinholeSpec spec;
    spec.pose = look_pose(eye, s.centre);
    // A field of view a little narrower than the bunny, with an off-centre principal point and
    // non-square pixels.
    spec.intrinsics = {0.9 * w, 0.8 * w, 0.45 * w, 0.55 * h, w, h};
    return spec;
}

TEST(ScanPinhole, EveryPixelMatchesBruteForce) {
    const BunnyScene s;
    const FilteredBruteForce oracle(s.tris);
    const auto w = static_cast<uint32_t>(std::max<size_t>(8, scaled(64)));
    const uint32_t h = w * 3 / 4;
    for (const DepthKind kind : {DepthKind::kDepth, DepthKind::kRange}) {
        for (const float min_range : {0.0f, static_cast<float>(2.3 * s.radius)}) {
            PinholeSpec spec = bunny_camera(s, w, h);
            spec.kind = kind;
            spec.normals = true;
            spec.min_range = min_range;
            const DepthImage image = scan_pinhole(s.tree, spec);
            ASSERT_EQ(image.width, w);
            ASSERT_EQ(image.height, h);
            ASSERT_EQ(image.depth.size(), size_t{w} * h);
            ASSERT_EQ(image.normals.size(), size_t{w} * h);
            size_t hits = 0, bad = 0;
            for (uint32_t j = 0; j < h; ++j) {
                for (uint32_t i = 0; i < w; ++i) {
                    const double v[3] = {(i + 0.5 - spec.intrinsics.cx) / spec.intrinsics.fx,
                                         (j + 0.5 - spec.intrinsics.cy) / spec.intrinsics.fy, 1.0};
                    const Ray ray = documented_ray(spec.pose, v, min_range, INFINITY);
                    const Hit want = oracle.intersect(ray);
                    const size_t p = size_t{j} * w + i;
                    float want_depth = INFINITY;
                    Vec3 want_normal{};
                    if (want.is_hit()) {
                        ++hits;
                        const double cosine =
                            1.0 / std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
                        want_depth = kind == DepthKind::kRange
                                         ? want.t
                                         : static_cast<float>(double{want.t} * cosine);
                        want_normal = triangle_normal(s.tris[want.prim]);
                    }
                    const bool same = image.prim[p] == want.prim &&
                                      same_float(image.depth[p], want_depth) &&
                                      std::memcmp(&image.normals[p], &want_normal, 12) == 0;
                    if (!same && ++bad <= 5)
                        ADD_FAILURE() << "pixel (" << i << ", " << j << "): prim " << image.prim[p]
                                      << " depth " << image.depth[p] << ", brute force prim "
                                      << want.prim << " depth " << want_depth;
                }
            }
            EXPECT_EQ(bad, 0u);
            EXPECT_GT(hits, size_t{w} * h / 8) << "the bunny should fill part of the image";
            EXPECT_LT(hits, size_t{w} * h) << "some pixels should miss";
        }
    }
}

TEST(ScanPinhole, DepthIsRangeTimesCosineAndPlanesHaveConstantDepth) {
    // Looking straight at the box face z = -1 from z = -5: every hit has depth 4.
    const Mesh mesh = box_mesh(-1, 1);
    const KdTree tree = build_kdtree(mesh);
    PinholeSpec spec;
    spec.pose.m[11] = -5.0;  // identity rotation: camera +z = world +z
    spec.intrinsics = {40.0, 40.0, 16.0, 12.0, 32, 24};
    spec.kind = DepthKind::kDepth;
    const DepthImage depth = scan_pinhole(tree, spec);
    spec.kind = DepthKind::kRange;
    const DepthImage range = scan_pinhole(tree, spec);
    size_t hits = 0;
    for (uint32_t j = 0; j < 24; ++j) {
        for (uint32_t i = 0; i < 32; ++i) {
            const size_t p = size_t{j} * 32 + i;
            ASSERT_EQ(depth.prim[p], range.prim[p]);
            // Pixel centres at +-(k + 0.5)/40 reach at most 0.4 x 4 = 1.6 > 1: the outer ring
            // misses.
            const double x = (i + 0.5 - 16.0) / 40.0 * 4.0, y = (j + 0.5 - 12.0) / 40.0 * 4.0;
            const bool inside = std::fabs(x) < 1.0 && std::fabs(y) < 1.0;
            if (std::fabs(std::fabs(x) - 1.0) < 1e-3 || std::fabs(std::fabs(y) - 1.0) < 1e-3)
                continue;  // pixel centres on the silhouette edge
            ASSERT_EQ(depth.prim[p] != kNoHit, inside) << i << "," << j;
            if (!inside) {
                EXPECT_EQ(depth.depth[p], INFINITY);
                EXPECT_EQ(range.depth[p], INFINITY);
                continue;
            }
            ++hits;
            EXPECT_NEAR(depth.depth[p], 4.0f, 4e-6f);
            const double cosine = 1.0 / std::sqrt(x * x / 16.0 + y * y / 16.0 + 1.0);
            EXPECT_NEAR(range.depth[p], 4.0 / cosine, 4e-5) << i << "," << j;
            EXPECT_EQ(depth.depth[p], static_cast<float>(double{range.depth[p]} * cosine));
            EXPECT_LE(depth.depth[p], range.depth[p]);
        }
    }
    EXPECT_GT(hits, 100u);
}

TEST(ScanPinhole, CentrePixelLooksAlongTheOpticalAxis) {
    PinholeSpec spec;
    const double eye[3] = {1, 2, 3}, target[3] = {-2, 0.5, 7};
    spec.pose = look_pose(eye, target);
    spec.intrinsics = {100, 100, 2.5, 1.5, 5, 3};  // pixel (2, 1) centre = principal point
    const Ray r = pinhole_ray(spec, 2, 1);
    EXPECT_EQ(r.dx, static_cast<float>(spec.pose.m[2]));
    EXPECT_EQ(r.dy, static_cast<float>(spec.pose.m[6]));
    EXPECT_EQ(r.dz, static_cast<float>(spec.pose.m[10]));
    EXPECT_EQ(r.ox, 1.0f);
    // +x right, +y down: pixel (4, 1) is to the right of the axis, pixel (2, 2) below it.
    const Ray right = pinhole_ray(spec, 4, 1), down = pinhole_ray(spec, 2, 2);
    const double rx =
        right.dx * spec.pose.m[0] + right.dy * spec.pose.m[4] + right.dz * spec.pose.m[8];
    const double dy =
        down.dx * spec.pose.m[1] + down.dy * spec.pose.m[5] + down.dz * spec.pose.m[9];
    EXPECT_GT(rx, 0.0);
    EXPECT_GT(dy, 0.0);
}

TEST(ScanPinhole, LookAtCameraGoesThroughTheRenderersPixels) {
    CameraSpec cam;
    cam.eye = {0.3f, 0.8f, 2.5f};
    cam.look_at = {0.0f, 0.1f, 0.0f};
    cam.up = {0.0f, 1.0f, 0.0f};
    cam.fov_deg = 50.0f;
    const PinholeCamera pin = pinhole_from_look_at(cam, 40, 30);
    EXPECT_NO_THROW(validate_pose(pin.pose));
    PinholeSpec spec;
    spec.intrinsics = pin.intrinsics;
    spec.pose = pin.pose;
    const Camera renderer(cam, 40, 30);
    for (uint32_t j = 0; j < 30; j += 7) {
        for (uint32_t i = 0; i < 40; i += 3) {
            const Ray a = pinhole_ray(spec, i, j);
            const Ray b = renderer.ray(i + 0.5f, j + 0.5f);
            EXPECT_NEAR(a.dx, b.dx, 2e-6f);
            EXPECT_NEAR(a.dy, b.dy, 2e-6f);
            EXPECT_NEAR(a.dz, b.dz, 2e-6f);
            EXPECT_EQ(a.ox, b.ox);
        }
    }
    cam.projection = Projection::kOrthographic;
    try {
        (void)pinhole_from_look_at(cam, 40, 30);
        ADD_FAILURE() << "an orthographic camera was accepted";
    } catch (const ScanError& e) {
        EXPECT_EQ(e.field(), "camera.projection");
    }
    cam.projection = Projection::kPerspective;
    cam.fov_deg = 180.0f;
    EXPECT_THROW((void)pinhole_from_look_at(cam, 40, 30), CameraError);
}

LidarSpec lidar_at(const double origin[3], uint32_t channels, uint32_t steps) {
    LidarSpec spec;
    spec.elevation_deg = lidar_elevations(-25.0, 15.0, channels);
    spec.azimuth_steps = steps;
    // Rotated 30 degrees about z and tilted 10 degrees about x.
    const double a = 30.0 * std::numbers::pi / 180.0, b = 10.0 * std::numbers::pi / 180.0;
    const double rz[3][3] = {
        {std::cos(a), -std::sin(a), 0}, {std::sin(a), std::cos(a), 0}, {0, 0, 1}};
    const double rx[3][3] = {
        {1, 0, 0}, {0, std::cos(b), -std::sin(b)}, {0, std::sin(b), std::cos(b)}};
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) {
            double s = 0;
            for (int k = 0; k < 3; ++k) s += rz[r][k] * rx[k][c];
            spec.pose.m[4 * r + c] = s;
        }
        spec.pose.m[4 * r + 3] = origin[r];
    }
    return spec;
}

/// Every beam's returns equal brute_force_intersect_all's nearest (merged) hits of the ray built
/// from the documented conventions; returns the number of points.
size_t check_lidar_cloud(const PointCloud& cloud, std::span<const TriVerts> tris,
                         const LidarSpec& spec) {
    const auto channels = static_cast<uint32_t>(spec.elevation_deg.size());
    EXPECT_EQ(cloud.channels, channels);
    EXPECT_EQ(cloud.azimuth_steps, spec.azimuth_steps);
    size_t next = 0, bad = 0;
    for (uint32_t a = 0; a < spec.azimuth_steps; ++a) {
        for (uint32_t c = 0; c < channels; ++c) {
            const double e = spec.elevation_deg[c] * std::numbers::pi / 180.0;
            const double az = 2.0 * std::numbers::pi * a / spec.azimuth_steps;
            const double v[3] = {std::cos(e) * std::cos(az), std::cos(e) * std::sin(az),
                                 std::sin(e)};
            const Ray ray = documented_ray(spec.pose, v, spec.min_range, spec.max_range);
            const std::vector<Hit> want = brute_force_intersect_all(tris, ray, true);
            const size_t n = std::min<size_t>(want.size(), spec.returns);
            for (size_t k = 0; k < n; ++k, ++next) {
                if (next >= cloud.points.size()) {
                    ADD_FAILURE() << "the cloud has too few points";
                    return cloud.points.size();
                }
                const LidarPoint& got = cloud.points[next];
                const Vec3 p = hit_point(tris[want[k].prim], want[k]);
                const bool same = got.channel == c && got.azimuth_index == a &&
                                  got.return_index == k && got.prim == want[k].prim &&
                                  same_float(got.range, want[k].t) && same_float(got.x, p.x) &&
                                  same_float(got.y, p.y) && same_float(got.z, p.z) &&
                                  got.range >= spec.min_range && got.range <= spec.max_range;
                if (!same && ++bad <= 5)
                    ADD_FAILURE() << "beam (" << c << ", " << a << ") return " << k << ": prim "
                                  << got.prim << " range " << got.range << ", brute force prim "
                                  << want[k].prim << " range " << want[k].t;
            }
        }
    }
    EXPECT_EQ(next, cloud.points.size()) << "the cloud has extra points";
    EXPECT_EQ(bad, 0u);
    return cloud.points.size();
}

/// Two spheres, one around the origin and one beside it, inside a box [-3, 3]^3: a lidar near
/// the origin sees every beam return, most of them twice or more.
Mesh spheres_in_box() {
    Mesh mesh = box_mesh(-3, 3);
    append(mesh, uv_sphere({0.2f, 0.1f, 0.0f}, 1.0f, 12, 24));
    append(mesh, uv_sphere({1.8f, -0.5f, 0.3f}, 0.6f, 10, 20));
    return mesh;
}

size_t check_lidar(const KdTree& tree, std::span<const TriVerts> tris, const LidarSpec& spec) {
    return check_lidar_cloud(scan_lidar(tree, spec), tris, spec);
}

TEST(ScanLidar, TiledScanMatchesBruteForceOnEveryIsaWithPartialTiles) {
    // scan_lidar traces the beams in tiles (detail::lidar_tile_order: 8 azimuth steps of one
    // channel, blocks of 64 x 16) and writes the cloud back in beam order: every point equals
    // brute force's, in beam order, on every ISA, for sizes with partial tiles and blocks, one
    // and two returns. From inside nested spheres in a box: every beam returns, most twice.
    const KdTree tree = build_kdtree(spheres_in_box());
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    const double origin[3] = {0.1, 0.0, 0.05};
    for (const auto& [channels, steps] :
         {std::pair{19u, 150u}, std::pair{3u, 13u}, std::pair{16u, 64u}, std::pair{1u, 9u}}) {
        LidarSpec spec = lidar_at(origin, channels, steps);
        for (const uint32_t returns : {1u, 2u}) {
            spec.returns = returns;
            const PointCloud public_scan = scan_lidar(tree, spec);
            for (const Isa isa : supported_isas()) {
                SCOPED_TRACE(std::to_string(channels) + " x " + std::to_string(steps) + ", " +
                             std::to_string(returns) + " returns, " + std::string(isa_name(isa)));
                const PointCloud cloud = detail::scan_lidar(tree, spec, isa);
                EXPECT_EQ(cloud.returns, returns);
                const size_t n = check_lidar_cloud(cloud, tris, spec);
                EXPECT_GE(n, size_t{channels} * steps) << "every beam hits the inner sphere";
                if (returns == 2) {
                    EXPECT_GT(n, size_t{channels} * steps);
                }
                // The public scan (the default ISA) is the same cloud, bit for bit.
                ASSERT_EQ(cloud.points.size(), public_scan.points.size());
                EXPECT_EQ(std::memcmp(cloud.points.data(), public_scan.points.data(),
                                      n * sizeof(LidarPoint)),
                          0);
            }
        }
    }
}

TEST(ScanLidar, ReturnsMatchBruteForceOnTheBunny) {
    const BunnyScene s;
    const double origin[3] = {s.centre[0] + 1.5 * s.radius, s.centre[1],
                              s.centre[2] + 0.3 * s.radius};
    const auto steps = static_cast<uint32_t>(std::max<size_t>(16, scaled(72)));
    LidarSpec spec = lidar_at(origin, 10, steps);
    spec.returns = 3;
    const size_t all = check_lidar(s.tree, s.tris, spec);
    EXPECT_GT(all, steps / 2) << "the bunny should fill part of the view";
    // A range window drops the near and far hits.
    spec.min_range = static_cast<float>(1.2 * s.radius);
    spec.max_range = static_cast<float>(1.8 * s.radius);
    spec.returns = 1;
    const size_t windowed = check_lidar(s.tree, s.tris, spec);
    EXPECT_GT(windowed, steps / 8);
    EXPECT_LT(windowed, all);
}

TEST(ScanLidar, ReturnsMatchBruteForceInsideNestedSpheres) {
    // From inside: every beam crosses the inner sphere's far side... and the outer box.
    const KdTree tree = build_kdtree(spheres_in_box());
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    const double origin[3] = {0.1, 0.0, 0.05};
    LidarSpec spec = lidar_at(origin, 8, static_cast<uint32_t>(std::max<size_t>(8, scaled(90))));
    spec.returns = 4;
    const size_t n = check_lidar(tree, tris, spec);
    EXPECT_GT(n, 8u * spec.azimuth_steps) << "every beam hits at least the inner sphere";
}

TEST(ScanLidar, DirectionConventions) {
    // The box [-1, 1]^3 from the origin with the identity pose: azimuth 0 is +x, a quarter turn
    // is +y (counter-clockwise from above), a positive elevation goes up.
    const Mesh mesh = box_mesh(-1, 1);
    const KdTree tree = build_kdtree(mesh);
    LidarSpec spec;
    spec.elevation_deg = {30.0};
    spec.azimuth_steps = 4;
    const PointCloud cloud = scan_lidar(tree, spec);
    ASSERT_EQ(cloud.points.size(), 4u);
    EXPECT_FLOAT_EQ(cloud.points[0].x, 1.0f);
    EXPECT_NEAR(cloud.points[0].y, 0.0f, 1e-6f);
    EXPECT_FLOAT_EQ(cloud.points[1].y, 1.0f);
    EXPECT_NEAR(cloud.points[1].x, 0.0f, 1e-6f);
    EXPECT_FLOAT_EQ(cloud.points[2].x, -1.0f);
    EXPECT_FLOAT_EQ(cloud.points[3].y, -1.0f);
    for (const LidarPoint& p : cloud.points) {
        EXPECT_NEAR(p.z, std::tan(30.0 * std::numbers::pi / 180.0), 1e-6);
        EXPECT_NEAR(p.range, 1.0 / std::cos(30.0 * std::numbers::pi / 180.0), 1e-6);
    }
    const std::vector<double> e = lidar_elevations(-10.0, 20.0, 4);
    EXPECT_EQ(e, (std::vector<double>{20.0, 10.0, 0.0, -10.0}));
    EXPECT_EQ(lidar_elevations(-10.0, 20.0, 1), std::vector<double>{5.0});
}

TEST(ScanLidar, BeamThroughASharedEdgeGivesOneReturn) {
    // Azimuth 45 degrees at elevation 0 runs into the box's vertical edge x = y = 1, shared by the
    // faces x = 1 and y = 1: two triangles hit at one t, one return.
    const Mesh mesh = box_mesh(-1, 1);
    const KdTree tree = build_kdtree(mesh);
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    LidarSpec spec;
    spec.elevation_deg = {0.0};
    spec.azimuth_steps = 8;
    spec.returns = 4;
    const Ray beam = lidar_ray(spec, 0, 1);
    ASSERT_EQ(beam.dx, beam.dy);
    ASSERT_GE(brute_force_intersect_all(tris, beam, false).size(), 2u)
        << "the beam should hit both triangles at the edge";
    const PointCloud cloud = scan_lidar(tree, spec);
    size_t at_edge = 0;
    for (const LidarPoint& p : cloud.points) at_edge += p.azimuth_index == 1;
    EXPECT_EQ(at_edge, 1u);
    EXPECT_EQ(cloud.points.size(), 8u) << "one return per beam from inside a closed box";
    check_lidar(tree, tris, spec);
}

TEST(Scan, SameBytesAtOneAndTwoThreads) {
    const BunnyScene s;
    PinholeSpec pin = bunny_camera(s, 96, 64);
    pin.normals = true;
    const double origin[3] = {s.centre[0] + 1.5 * s.radius, s.centre[1],
                              s.centre[2] + 0.3 * s.radius};
    LidarSpec lidar = lidar_at(origin, 32, 256);
    lidar.returns = 2;
    DepthImage images[2];
    PointCloud clouds[2];
    for (int threads = 1; threads <= 2; ++threads) {
        tbb::task_arena arena(threads);
        arena.execute([&] {
            images[threads - 1] = scan_pinhole(s.tree, pin);
            clouds[threads - 1] = scan_lidar(s.tree, lidar);
        });
    }
    ASSERT_EQ(images[0].depth.size(), images[1].depth.size());
    EXPECT_EQ(
        std::memcmp(images[0].depth.data(), images[1].depth.data(), images[0].depth.size() * 4), 0);
    EXPECT_EQ(images[0].prim, images[1].prim);
    EXPECT_EQ(std::memcmp(images[0].normals.data(), images[1].normals.data(),
                          images[0].normals.size() * sizeof(Vec3)),
              0);
    ASSERT_EQ(clouds[0].points.size(), clouds[1].points.size());
    ASSERT_GT(clouds[0].points.size(), 100u);
    EXPECT_EQ(std::memcmp(clouds[0].points.data(), clouds[1].points.data(),
                          clouds[0].points.size() * sizeof(LidarPoint)),
              0);
}

template <class F>
void expect_field(const char* field, F&& f) {
    try {
        f();
        ADD_FAILURE() << "no ScanError for " << field;
    } catch (const ScanError& e) {
        EXPECT_EQ(e.field(), field) << e.what();
        EXPECT_NE(std::string(e.what()).find(std::string(field).substr(0, 4)), std::string::npos)
            << e.what();
    }
}

TEST(Scan, EachValidationErrorNamesItsField) {
    const Mesh mesh = box_mesh(-1, 1);
    const KdTree tree = build_kdtree(mesh);
    const PinholeSpec good{{10, 10, 2, 2, 4, 4}, Pose{}, DepthKind::kDepth, false, 0.0f, INFINITY};
    EXPECT_NO_THROW(validate(good));
    auto pin = [&](auto edit) {
        return [&tree, good, edit] {
            PinholeSpec s = good;
            edit(s);
            (void)scan_pinhole(tree, s);
        };
    };
    expect_field("intrinsics.fx", pin([](PinholeSpec& s) { s.intrinsics.fx = 0; }));
    expect_field("intrinsics.fx", pin([](PinholeSpec& s) { s.intrinsics.fx = -3; }));
    expect_field("intrinsics.fy", pin([](PinholeSpec& s) { s.intrinsics.fy = NAN; }));
    expect_field("intrinsics.cx", pin([](PinholeSpec& s) { s.intrinsics.cx = INFINITY; }));
    expect_field("intrinsics.cy", pin([](PinholeSpec& s) { s.intrinsics.cy = NAN; }));
    expect_field("intrinsics.width", pin([](PinholeSpec& s) { s.intrinsics.width = 0; }));
    expect_field("intrinsics.height", pin([](PinholeSpec& s) { s.intrinsics.height = 0; }));
    expect_field("min_range", pin([](PinholeSpec& s) { s.min_range = -1; }));
    expect_field("min_range", pin([](PinholeSpec& s) { s.min_range = INFINITY; }));
    expect_field("max_range", pin([](PinholeSpec& s) { s.max_range = 0; }));
    expect_field("max_range", pin([](PinholeSpec& s) { s.max_range = NAN; }));
    expect_field("output", pin([](PinholeSpec& s) { s.kind = static_cast<DepthKind>(7); }));
    expect_field("pose", pin([](PinholeSpec& s) { s.pose.m[5] = NAN; }));
    expect_field("pose", pin([](PinholeSpec& s) { s.pose.m[14] = 1; }));
    expect_field("pose", pin([](PinholeSpec& s) { s.pose.m[0] = 2; }));    // scaled
    expect_field("pose", pin([](PinholeSpec& s) { s.pose.m[1] = 0.1; }));  // sheared
    expect_field("pose", pin([](PinholeSpec& s) { s.pose.m[10] = -1; }));  // a reflection
    // Within tolerance passes; a float-rounded rotation is rigid enough.
    PinholeSpec nearly = good;
    nearly.pose.m[0] = 1.0 + 0.4 * kPoseTolerance;
    EXPECT_NO_THROW(validate(nearly));

    LidarSpec lidar;
    lidar.elevation_deg = {0.0, 5.0};
    lidar.azimuth_steps = 8;
    EXPECT_NO_THROW(validate(lidar));
    auto lid = [&](auto edit) {
        return [&tree, lidar, edit] {
            LidarSpec s = lidar;
            edit(s);
            (void)scan_lidar(tree, s);
        };
    };
    expect_field("elevation_deg", lid([](LidarSpec& s) { s.elevation_deg.clear(); }));
    expect_field("elevation_deg[1]", lid([](LidarSpec& s) { s.elevation_deg[1] = 91; }));
    expect_field("elevation_deg[0]", lid([](LidarSpec& s) { s.elevation_deg[0] = NAN; }));
    expect_field("azimuth_steps", lid([](LidarSpec& s) { s.azimuth_steps = 0; }));
    expect_field("returns", lid([](LidarSpec& s) { s.returns = 0; }));
    expect_field("returns", lid([](LidarSpec& s) { s.returns = kMaxHitsPerRay + 1; }));
    expect_field("min_range", lid([](LidarSpec& s) { s.min_range = NAN; }));
    expect_field("max_range", lid([](LidarSpec& s) { s.max_range = -1; }));
    expect_field("pose", lid([](LidarSpec& s) { s.pose.m[3] = INFINITY; }));
    expect_field("vertical_fov", [] { (void)lidar_elevations(10, -10, 4); });
    expect_field("vertical_fov", [] { (void)lidar_elevations(-91, 10, 4); });
    expect_field("vertical_fov", [] { (void)lidar_elevations(NAN, 10, 4); });
    expect_field("channels", [] { (void)lidar_elevations(-10, 10, 0); });
}

}  // namespace
}  // namespace kdrt::test
