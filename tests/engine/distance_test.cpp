// Distance queries (kdrt/distance.h): the kD-tree search equals the brute-force oracle bit for
// bit (random soups, the bunny, points on vertices and edges, near and far, with a maximum
// distance); the point-triangle routine against dense sampling; the tie rule; the sign against
// the analytic answer on cubes and spheres and against ray parity on closed data meshes; open,
// misoriented and non-manifold meshes report the side as unknown.

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>

#include <tbb/task_arena.h>

#include "kdrt/distance.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/query.h"
#include "scenes.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

Mesh load_data_mesh(const char* name) {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/" + name);
    if (!mesh) throw std::runtime_error(mesh.error().to_string());
    return std::move(mesh).value();
}

float diagonal_of(const KdTree& tree) {
    const Vec3 e = tree.bounds.extent();
    return std::sqrt(dot(e, e));
}

bool same_bits(const ClosestPoint& a, const ClosestPoint& b) {
    return std::memcmp(&a.distance, &b.distance, 4) == 0 && a.prim == b.prim &&
           std::memcmp(&a.u, &b.u, 4) == 0 && std::memcmp(&a.v, &b.v, 4) == 0 &&
           std::memcmp(&a.point, &b.point, sizeof(Vec3)) == 0 && a.feature == b.feature &&
           a.side == b.side;
}

/// Tree against brute force for every point, unsigned and signed, without a limit and with
/// `max_distance`; returns how many were found within the limit.
size_t check_against_brute_force(const KdTree& tree, const SurfaceIndex& index,
                                 std::span<const Vec3> points, float max_distance) {
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    size_t bad = 0, found_within = 0;
    for (const float limit : {INFINITY, max_distance}) {
        for (const bool sign : {false, true}) {
            const DistanceOptions options{limit, sign};
            for (size_t i = 0; i < points.size(); ++i) {
                const ClosestPoint got = closest_point(tree, index, points[i], options);
                const ClosestPoint want =
                    brute_force_closest_point(tris, index, points[i], options);
                if (!same_bits(got, want) && ++bad <= 5)
                    ADD_FAILURE() << "point " << i << " limit " << limit << ": tree prim "
                                  << got.prim << " d " << got.distance << ", brute force prim "
                                  << want.prim << " d " << want.distance;
                if (limit == max_distance && !sign && want.found()) ++found_within;
            }
        }
    }
    EXPECT_EQ(bad, 0u);
    return found_within;
}

/// Points around `mesh`: uniform in its box grown by half its size, on and just off its surface,
/// exactly on its vertices and on its edges.
std::vector<Vec3> query_points(Rng& rng, const Mesh& mesh, const KdTree& tree, size_t count) {
    const Vec3 ext = tree.bounds.extent();
    const Aabb big{tree.bounds.lo - ext * 0.5f, tree.bounds.hi + ext * 0.5f};
    const float scale = std::max({ext.x, ext.y, ext.z});
    std::vector<Vec3> points;
    for (size_t i = 0; i < count; ++i) {
        const auto tri = rng.below(static_cast<uint32_t>(mesh.triangle_count()));
        const Vec3 a = mesh.corner(tri, 0), b = mesh.corner(tri, 1), c = mesh.corner(tri, 2);
        float u = rng.uniform(), v = rng.uniform();
        if (u + v > 1) u = 1 - u, v = 1 - v;
        const Vec3 on = a * (1 - u - v) + b * u + c * v;
        switch (rng.below(6)) {
            case 0:
                points.push_back(rng.in_box(big));
                break;
            case 1:
                points.push_back(on);
                break;
            case 2:
                points.push_back(on + rng.on_sphere() * (scale * 1e-3f * rng.uniform()));
                break;
            case 3:
                points.push_back(a);
                break;
            case 4:
                points.push_back(a + (b - a) * rng.uniform());
                break;
            default: {  // far away: 10^3 .. 10^16 mesh sizes from its centre
                const float far = scale * std::pow(10.0f, static_cast<float>(3 + rng.below(14)));
                points.push_back((tree.bounds.lo + tree.bounds.hi) * 0.5f + rng.on_sphere() * far);
                break;
            }
        }
    }
    return points;
}

TEST(ClosestOnTriangle, RegionsOfARightTriangle) {
    const TriVerts tri{{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
    struct Case {
        double p[3];
        Feature feature;
        double d2, u, v;
    };
    const Case cases[] = {
        {{0.25, 0.25, 2}, Feature::kFace, 4, 0.25, 0.25},
        {{-1, -1, 0}, Feature::kVertex0, 2, 0, 0},
        {{2, -1, 1}, Feature::kVertex1, 3, 1, 0},
        {{-1, 3, 0}, Feature::kVertex2, 5, 0, 1},
        {{0.5, -1, 3}, Feature::kEdge01, 10, 0.5, 0},
        {{-2, 0.75, 0}, Feature::kEdge20, 4, 0, 0.75},
        {{1, 1, 0}, Feature::kEdge12, 0.5, 0.5, 0.5},
        {{0.5, 0.5, 0}, Feature::kEdge12, 0, 0.5, 0.5},
        {{0, 0, 0}, Feature::kVertex0, 0, 0, 0},
    };
    for (const Case& c : cases) {
        SCOPED_TRACE(testing::Message() << c.p[0] << " " << c.p[1] << " " << c.p[2]);
        const TriangleClosest r = closest_on_triangle(tri, c.p);
        EXPECT_EQ(r.feature, c.feature);
        EXPECT_DOUBLE_EQ(r.d2, c.d2);
        EXPECT_DOUBLE_EQ(r.u, c.u);
        EXPECT_DOUBLE_EQ(r.v, c.v);
    }
    const TriVerts point{{1, 2, 3}, {1, 2, 3}, {1, 2, 3}};
    const TriVerts line{{0, 0, 0}, {1, 1, 1}, {2, 2, 2}};
    const double p[3] = {1, 2, 3};
    EXPECT_EQ(closest_on_triangle(point, p).feature, Feature::kNone);
    EXPECT_EQ(closest_on_triangle(line, p).feature, Feature::kNone);
}

TEST(ClosestOnTriangle, NoSampledPointOfTheTriangleIsCloser) {
    Rng rng(test_seed() + 30);
    for (size_t i = 0; i < scaled(300); ++i) {
        const Vec3 c = rng.on_sphere();
        // Some slivers: one corner close to the line of the other two.
        const Vec3 a = c + rng.on_sphere(), b = c + rng.on_sphere();
        const Vec3 d =
            i % 3 == 0 ? a + (b - a) * 0.3f + rng.on_sphere() * 1e-4f : c + rng.on_sphere();
        const TriVerts tri{{a.x, a.y, a.z}, {b.x, b.y, b.z}, {d.x, d.y, d.z}};
        const Vec3 p = rng.on_sphere() * 3.0f;
        const double q[3] = {p.x, p.y, p.z};
        const TriangleClosest r = closest_on_triangle(tri, q);
        ASSERT_NE(r.feature, Feature::kNone);
        // The reported point is the barycentric point, on the triangle.
        EXPECT_GE(r.u, 0.0);
        EXPECT_GE(r.v, 0.0);
        EXPECT_LE(r.u + r.v, 1.0 + 1e-12);
        for (int k = 0; k < 3; ++k)
            EXPECT_NEAR(r.point[k], (1 - r.u - r.v) * a[k] + r.u * b[k] + r.v * d[k], 1e-9);
        for (int s = 0; s <= 40; ++s) {
            for (int t = 0; s + t <= 40; ++t) {
                const double u = s / 40.0, v = t / 40.0;
                double d2 = 0;
                for (int k = 0; k < 3; ++k) {
                    const double x = (1 - u - v) * a[k] + u * b[k] + v * d[k] - q[k];
                    d2 += x * x;
                }
                ASSERT_GE(d2, r.d2 - 1e-9) << "sample " << u << ", " << v;
            }
        }
    }
}

TEST(Distance, RandomSoupsMatchBruteForce) {
    const uint64_t seed = test_seed();
    for (uint64_t s = seed; s < seed + 3; ++s) {
        SCOPED_TRACE(testing::Message() << "seed=" << s);
        Rng rng(s);
        const Mesh mesh = random_soup(rng, 1500, 0.05f + 0.1f * static_cast<float>(s - seed));
        const KdTree tree = build_kdtree(mesh);
        const SurfaceIndex index = build_surface_index(tree);
        EXPECT_FALSE(index.closed);
        const std::vector<Vec3> points = query_points(rng, mesh, tree, scaled(2000));
        const size_t within = check_against_brute_force(tree, index, points, 0.02f);
        EXPECT_GT(within, points.size() / 4);
        EXPECT_LT(within, points.size());
    }
}

TEST(Distance, MiddleTreeMatchesBruteForce) {
    Rng rng(test_seed() + 31);
    const Mesh mesh = random_soup(rng, 1000, 0.1f);
    BuildOptions options;
    options.builder = Builder::kMiddle;
    const KdTree tree = build_kdtree(mesh, options);
    const std::vector<Vec3> points = query_points(rng, mesh, tree, scaled(1000));
    check_against_brute_force(tree, build_surface_index(tree), points, 0.05f);
}

TEST(Distance, BunnyMatchesBruteForce) {
    const Mesh mesh = load_data_mesh("bunny00.off");
    const KdTree tree = build_kdtree(mesh);
    const SurfaceIndex index = build_surface_index(tree);
    Rng rng(test_seed() + 32);
    const std::vector<Vec3> points = query_points(rng, mesh, tree, scaled(300));
    check_against_brute_force(tree, index, points, 0.002f);
}

TEST(Distance, PointsOnTheSurfaceAreAtDistanceZero) {
    Rng rng(test_seed() + 33);
    const Mesh mesh = random_soup(rng, 500, 0.1f);
    const KdTree tree = build_kdtree(mesh);
    const SurfaceIndex index = build_surface_index(tree);
    for (size_t i = 0; i < scaled(500); ++i) {
        const auto tri = rng.below(static_cast<uint32_t>(mesh.triangle_count()));
        const Vec3 p = mesh.corner(tri, static_cast<int>(rng.below(3)));
        // Exactly on a vertex: found at distance 0, even with max_distance 0.
        const ClosestPoint c = closest_point(tree, index, p, {0.0f, false});
        ASSERT_TRUE(c.found());
        EXPECT_EQ(c.distance, 0.0f);
        EXPECT_EQ(c.point, p);
    }
}

TEST(Distance, TiesGoToTheLowestPrim) {
    // Triangle 0 and triangle 2 are the same; triangle 1 is the mirror image of 0 in z = 0, so a
    // point in the plane z = 0 is as far from all three.
    Mesh mesh;
    add_triangle(mesh, {0, 0, 1}, {1, 0, 1}, {0, 1, 1});
    add_triangle(mesh, {0, 0, -1}, {1, 0, -1}, {0, 1, -1});
    add_triangle(mesh, {0, 0, 1}, {1, 0, 1}, {0, 1, 1});
    for (int i = 0; i < 200; ++i) add_triangle(mesh, {5.0f + i, 5, 5}, {6.0f + i, 5, 5}, {5, 6, 5});
    const KdTree tree = build_kdtree(mesh);
    const SurfaceIndex index = build_surface_index(tree);
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    for (const Vec3 p : {Vec3{0.2f, 0.2f, 0}, Vec3{-1, -1, 0}, Vec3{0.5f, -2, 0}}) {
        const ClosestPoint c = closest_point(tree, index, p, {});
        EXPECT_EQ(c.prim, 0u) << "z = 0: triangles 0, 1 and 2 tie, the lowest prim is 0";
        EXPECT_TRUE(same_bits(c, brute_force_closest_point(tris, index, p, {})));
    }
    // Above the plane, 0 and its copy 2 tie.
    const ClosestPoint up = closest_point(tree, index, {0.2f, 0.2f, 3}, {});
    EXPECT_EQ(up.prim, 0u);
    EXPECT_EQ(up.distance, 2.0f);
}

TEST(Distance, InvalidPointsAndLimitsFindNothing) {
    Rng rng(test_seed() + 34);
    const Mesh mesh = random_soup(rng, 100);
    const KdTree tree = build_kdtree(mesh);
    const SurfaceIndex index = build_surface_index(tree);
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    const float nan = std::nanf(""), inf = INFINITY;
    for (const Vec3 p : {Vec3{nan, 0, 0}, Vec3{0, inf, 0}, Vec3{0, 0, -inf}}) {
        EXPECT_FALSE(closest_point(tree, index, p, {}).found());
        EXPECT_FALSE(brute_force_closest_point(tris, index, p, {}).found());
    }
    for (const float limit : {nan, -1.0f}) {
        const ClosestPoint c = closest_point(tree, index, {0.5f, 0.5f, 0.5f}, {limit, true});
        EXPECT_FALSE(c.found());
        EXPECT_EQ(c.distance, inf);
        EXPECT_EQ(c.feature, Feature::kNone);
        EXPECT_EQ(c.side, Side::kUnknown);
        EXPECT_TRUE(std::isnan(c.point.x));
    }
    // The limit is inclusive: a point exactly max_distance away is found.
    Mesh one;
    add_triangle(one, {0, 0, 0}, {1, 0, 0}, {0, 1, 0});
    const KdTree t1 = build_kdtree(one);
    const SurfaceIndex i1 = build_surface_index(t1);
    EXPECT_TRUE(closest_point(t1, i1, {0.25f, 0.25f, 0.5f}, {0.5f, false}).found());
    EXPECT_FALSE(closest_point(t1, i1, {0.25f, 0.25f, 0.5f}, {0.4999f, false}).found());
    // An empty mesh, and a mesh of degenerate triangles only, have nothing to find.
    const KdTree empty = build_kdtree(Mesh{});
    EXPECT_FALSE(closest_point(empty, build_surface_index(empty), {0, 0, 0}, {}).found());
    Mesh flat;
    add_triangle(flat, {0, 0, 0}, {1, 1, 1}, {2, 2, 2});
    const KdTree degenerate = build_kdtree(flat);
    const SurfaceIndex di = build_surface_index(degenerate);
    EXPECT_EQ(di.degenerate_triangles, 1u);
    EXPECT_FALSE(di.closed);
    EXPECT_FALSE(closest_point(degenerate, di, {0, 0, 0}, {}).found());
}

TEST(Distance, BatchIsTheSameAtAnyThreadCount) {
    Rng rng(test_seed() + 35);
    const Mesh mesh = random_soup(rng, 2000);
    const KdTree tree = build_kdtree(mesh);
    const SurfaceIndex index = build_surface_index(tree);
    const std::vector<Vec3> points = query_points(rng, mesh, tree, scaled(3000));
    std::vector<ClosestPoint> one(points.size()), two(points.size());
    tbb::task_arena(1).execute([&] { closest_points(tree, index, points, one, {0.1f, true}); });
    tbb::task_arena(2).execute([&] { closest_points(tree, index, points, two, {0.1f, true}); });
    for (size_t i = 0; i < points.size(); ++i) {
        ASSERT_TRUE(same_bits(one[i], two[i])) << i;
        ASSERT_TRUE(same_bits(one[i], closest_point(tree, index, points[i], {0.1f, true}))) << i;
    }
}

TEST(Distance, FarPointsCostWhatPointsJustOutsideDo) {
    const Mesh mesh = load_data_mesh("bunny00.off");
    const KdTree tree = build_kdtree(mesh);
    const SurfaceIndex index = build_surface_index(tree);
    Rng rng(test_seed() + 37);
    SCOPED_TRACE(testing::Message() << "seed=" << test_seed() + 37);
    const float size = diagonal_of(tree);
    const Vec3 centre = (tree.bounds.lo + tree.bounds.hi) * 0.5f;
    // Points one bunny size from its centre: just outside it, where the pruning slack was
    // always small.
    std::vector<Vec3> close;
    for (size_t i = 0; i < 200; ++i) close.push_back(centre + rng.on_sphere() * size);
    std::vector<ClosestPoint> out(close.size());
    const uint64_t close_work = closest_points(tree, index, close, out, {}).work;
    ASSERT_GT(close_work, 0u);
    // A far point's search ends once the nearest waiting cell is beyond the best triangle, and
    // its slack does not grow with its distance: up to 10^8 sizes away, its work is that of a
    // point just outside, far below the triangle count (brute force's).
    for (const float far : {1e3f, 1e4f, 1e6f, 1e8f}) {
        SCOPED_TRACE(testing::Message() << "distance " << far << " sizes");
        std::vector<Vec3> points;
        for (size_t i = 0; i < close.size(); ++i)
            points.push_back(centre + rng.on_sphere() * (far * size));
        const uint64_t work = closest_points(tree, index, points, out, {}).work;
        EXPECT_LT(work, 2 * close_work) << "one size away: " << close_work;
        EXPECT_LT(work, points.size() * mesh.triangle_count() / 20);
        // Brute force over the bunny is the test's cost (48 s of the ASan pass): every point in
        // Release, the first test_scale() of them where the oracle loops are scaled.
        check_against_brute_force(
            tree, index, std::span<const Vec3>(points).first(scaled(points.size())), far * size);
    }
}

TEST(Distance, BatchStopsWhenCancelledOrOverItsWork) {
    Rng rng(test_seed() + 38);
    const Mesh mesh = random_soup(rng, 2000);
    const KdTree tree = build_kdtree(mesh);
    const SurfaceIndex index = build_surface_index(tree);
    const std::vector<Vec3> points = query_points(rng, mesh, tree, 4000);
    std::vector<ClosestPoint> out(points.size());
    const DistanceStats all = closest_points(tree, index, points, out, {});
    EXPECT_EQ(all.status, DistanceStatus::kDone);
    // The same limit as the work done is enough; one less is not, and the batch stops early.
    DistanceControl control;
    control.max_work = all.work;
    EXPECT_EQ(closest_points(tree, index, points, out, {}, control).status, DistanceStatus::kDone);
    control.max_work = all.work / 10;
    const DistanceStats capped = closest_points(tree, index, points, out, {}, control);
    EXPECT_EQ(capped.status, DistanceStatus::kOverWork);
    EXPECT_LT(capped.work, all.work);
    // Cancelled before it starts: nothing is searched. Cancelled by the poll hook: it stops.
    std::atomic<bool> cancel{true};
    control = {};
    control.cancel = &cancel;
    const DistanceStats none = closest_points(tree, index, points, out, {}, control);
    EXPECT_EQ(none.status, DistanceStatus::kCancelled);
    EXPECT_EQ(none.work, 0u);
    cancel = false;
    std::atomic<int> polls{0};
    control.poll = [&] {
        ++polls;
        cancel = true;
    };
    std::vector<Vec3> many;
    for (int k = 0; k < 20; ++k) many.insert(many.end(), points.begin(), points.end());
    std::vector<ClosestPoint> many_out(many.size());
    const DistanceStats polled = closest_points(tree, index, many, many_out, {}, control);
    EXPECT_EQ(polled.status, DistanceStatus::kCancelled);
    EXPECT_GE(polls.load(), 1);
    EXPECT_LT(polled.work, 20 * all.work);
}

/// The cube [lo, hi]^3, 12 triangles wound outwards, shared vertices.
Mesh cube(float lo = 0, float hi = 1) { return test::box_mesh(lo, hi); }

/// The exact signed distance to the unit cube (negative inside).
double cube_signed_distance(Vec3 p) {
    double out2 = 0, in = -1e30;
    for (int a = 0; a < 3; ++a) {
        const double d = std::max(-double{p[a]}, double{p[a]} - 1.0);  // > 0 outside this slab
        if (d > 0) out2 += d * d;
        in = std::max(in, d);
    }
    return out2 > 0 ? std::sqrt(out2) : in;
}

TEST(SignedDistance, CubeMatchesTheAnalyticDistance) {
    const Mesh mesh = cube();
    const KdTree tree = build_kdtree(mesh);
    const SurfaceIndex index = build_surface_index(tree);
    ASSERT_TRUE(index.closed);
    EXPECT_EQ(index.boundary_edges + index.nonmanifold_edges + index.misoriented_edges, 0u);
    Rng rng(test_seed() + 36);
    std::vector<Vec3> points;
    for (size_t i = 0; i < scaled(4000); ++i)
        points.push_back(rng.in_box({{-1, -1, -1}, {2, 2, 2}}));
    // Near the edges and corners, inside and out: each coordinate 0 or 1, pushed by up to 1e-3.
    for (size_t i = 0; i < scaled(4000); ++i) {
        Vec3 p;
        for (int a = 0; a < 3; ++a) {
            const float base = rng.below(3) == 0 ? rng.uniform() : static_cast<float>(rng.below(2));
            p[a] = base + rng.uniform(-1e-3f, 1e-3f);
        }
        points.push_back(p);
    }
    size_t inside = 0;
    for (const Vec3& p : points) {
        const double want = cube_signed_distance(p);
        const ClosestPoint c = closest_point(tree, index, p, {INFINITY, true});
        ASSERT_TRUE(c.found());
        EXPECT_NEAR(c.signed_distance(), want, 1e-6) << p.x << " " << p.y << " " << p.z;
        if (want != 0.0) {
            ASSERT_EQ(c.side, want < 0 ? Side::kInside : Side::kOutside)
                << p.x << " " << p.y << " " << p.z << " feature " << static_cast<int>(c.feature);
        }
        inside += c.side == Side::kInside;
    }
    EXPECT_GT(inside, points.size() / 10);
    // Exactly on a corner, an edge and a face: distance 0, outside.
    for (const Vec3 p : {Vec3{1, 1, 1}, Vec3{0.5f, 0, 1}, Vec3{0.25f, 0.5f, 0}}) {
        const ClosestPoint c = closest_point(tree, index, p, {INFINITY, true});
        EXPECT_EQ(c.distance, 0.0f);
        EXPECT_EQ(c.side, Side::kOutside);
    }
}

TEST(SignedDistance, FarPointsAreNeverInside) {
    // A closed 2-unit cube: from 10^16 away the closest feature is decided by rounding (it was
    // once a far face, whose normal then said "inside"). Outside the box, a point is outside.
    const Mesh mesh = cube(-1, 1);
    const KdTree tree = build_kdtree(mesh);
    const SurfaceIndex index = build_surface_index(tree);
    ASSERT_TRUE(index.closed);
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    Rng rng(test_seed() + 39);
    for (int e = 1; e <= 30; ++e) {
        const float far = std::pow(10.0f, static_cast<float>(e));
        for (int i = 0; i < 50; ++i) {
            const Vec3 p = rng.on_sphere() * far;
            const ClosestPoint c = closest_point(tree, index, p, {INFINITY, true});
            ASSERT_TRUE(c.found()) << "1e" << e;
            EXPECT_EQ(c.side, Side::kOutside)
                << "1e" << e << " " << p.x << " " << p.y << " " << p.z;
            EXPECT_TRUE(same_bits(c, brute_force_closest_point(tris, index, p, {INFINITY, true})));
        }
        for (const Vec3 axis : {Vec3{1, 0, 0}, Vec3{0, -1, 0}, Vec3{0, 0, 1}}) {
            const ClosestPoint c = closest_point(tree, index, axis * far, {INFINITY, true});
            EXPECT_EQ(c.side, Side::kOutside) << "1e" << e;
        }
    }
}

TEST(SignedDistance, SphereInsideIsInside) {
    const Mesh mesh = uv_sphere({0.1f, -0.2f, 0.3f}, 1.0f, 40, 80);
    const KdTree tree = build_kdtree(mesh);
    const SurfaceIndex index = build_surface_index(tree);
    ASSERT_TRUE(index.closed);
    Rng rng(test_seed() + 37);
    // The tessellation is within 1 - cos(pi / 40) < 0.0031 of the sphere.
    for (size_t i = 0; i < scaled(3000); ++i) {
        const float r = rng.uniform(0.0f, 2.0f);
        if (std::fabs(r - 1.0f) < 0.004f) continue;
        const Vec3 p = Vec3{0.1f, -0.2f, 0.3f} + rng.on_sphere() * r;
        const ClosestPoint c = closest_point(tree, index, p, {INFINITY, true});
        ASSERT_EQ(c.side, r < 1 ? Side::kInside : Side::kOutside) << r;
        EXPECT_NEAR(c.signed_distance(), r - 1.0f, 0.004f);
    }
    // Near its vertices (the poles and ring vertices, where the angle weights matter).
    for (size_t i = 0; i < scaled(2000); ++i) {
        const auto tri = rng.below(static_cast<uint32_t>(mesh.triangle_count()));
        const Vec3 v = mesh.corner(tri, static_cast<int>(rng.below(3)));
        const Vec3 n = (v - Vec3{0.1f, -0.2f, 0.3f});
        const float s = rng.uniform(-1e-3f, 1e-3f);
        if (std::fabs(s) < 1e-5f) continue;
        const Vec3 p = v + n * s + rng.on_sphere() * (std::fabs(s) * 0.2f);
        const ClosestPoint c = closest_point(tree, index, p, {INFINITY, true});
        ASSERT_EQ(c.side, s < 0 ? Side::kInside : Side::kOutside) << s;
    }
}

/// Side by ray parity (part 1's merged every-hit count): an odd number of crossings is inside.
Side parity_side(const KdTree& tree, Vec3 p, Rng& rng) {
    std::vector<Hit> hits;
    const Vec3 d = rng.on_sphere();
    intersect_all(tree, make_ray(p, d), true, hits);
    return hits.size() % 2 == 1 ? Side::kInside : Side::kOutside;
}

TEST(SignedDistance, ClosedDataMeshesAgreeWithRayParity) {
    for (const char* name : {"bunny00.off", "ChineseDragon-10kv.off", "diplodocus.off"}) {
        SCOPED_TRACE(name);
        const Mesh mesh = load_data_mesh(name);
        const KdTree tree = build_kdtree(mesh);
        const SurfaceIndex index = build_surface_index(tree);
        std::printf("%s: closed %d, boundary %u, non-manifold %u, misoriented %u, degenerate %u\n",
                    name, index.closed, index.boundary_edges, index.nonmanifold_edges,
                    index.misoriented_edges, index.degenerate_triangles);
        Rng rng(test_seed() + 38);
        const std::vector<Vec3> points = query_points(rng, mesh, tree, scaled(600));
        size_t agree = 0, compared = 0, inside = 0;
        for (const Vec3& p : points) {
            const ClosestPoint c = closest_point(tree, index, p, {INFINITY, true});
            if (!index.closed) {
                ASSERT_EQ(c.side, Side::kUnknown);
                continue;
            }
            // Parity is only trusted off the surface.
            if (c.distance < 1e-4f * diagonal_of(tree)) continue;
            ++compared;
            agree += c.side == parity_side(tree, p, rng);
            inside += c.side == Side::kInside;
        }
        if (index.closed) {
            EXPECT_EQ(agree, compared);
            EXPECT_GT(inside, 0u);
        }
    }
}

TEST(SignedDistance, OpenAndMisorientedMeshesHaveNoSide) {
    Mesh open;  // the cube without its top face
    {
        const Mesh c = cube();
        for (uint32_t t = 0; t < 12; ++t)
            if (t != 2 && t != 3)
                add_triangle(open, c.corner(t, 0), c.corner(t, 1), c.corner(t, 2));
    }
    Mesh flipped;  // one triangle wound the other way
    {
        const Mesh c = cube();
        for (uint32_t t = 0; t < 12; ++t)
            if (t == 5)
                add_triangle(flipped, c.corner(t, 0), c.corner(t, 2), c.corner(t, 1));
            else
                add_triangle(flipped, c.corner(t, 0), c.corner(t, 1), c.corner(t, 2));
    }
    Mesh fin = cube();  // a fin on an edge: three triangles there
    add_triangle(fin, {0, 0, 0}, {1, 0, 0}, {0.5f, -1, -1});
    struct Case {
        const Mesh* mesh;
        uint32_t boundary, nonmanifold, misoriented;
    };
    for (const Case& k : {Case{&open, 4, 0, 0}, Case{&flipped, 0, 0, 3}, Case{&fin, 2, 1, 0}}) {
        const KdTree tree = build_kdtree(*k.mesh);
        const SurfaceIndex index = build_surface_index(tree);
        EXPECT_FALSE(index.closed);
        EXPECT_EQ(index.boundary_edges, k.boundary);
        EXPECT_EQ(index.nonmanifold_edges, k.nonmanifold);
        EXPECT_EQ(index.misoriented_edges, k.misoriented);
        const ClosestPoint c = closest_point(tree, index, {0.5f, 0.5f, 0.5f}, {INFINITY, true});
        EXPECT_TRUE(c.found());
        EXPECT_EQ(c.side, Side::kUnknown);
        EXPECT_TRUE(std::isnan(c.signed_distance()));
    }
}

TEST(SignedDistance, SoupOfAClosedMeshIsClosed) {
    // Triangles given without shared indices: vertices are matched by position.
    const Mesh indexed = cube(-2, 3);
    Mesh soup;
    for (uint32_t t = 0; t < indexed.triangle_count(); ++t)
        add_triangle(soup, indexed.corner(t, 0), indexed.corner(t, 1), indexed.corner(t, 2));
    const KdTree tree = build_kdtree(soup);
    const SurfaceIndex index = build_surface_index(tree);
    EXPECT_TRUE(index.closed);
    EXPECT_EQ(closest_point(tree, index, {0, 0, 0}, {INFINITY, true}).side, Side::kInside);
    EXPECT_EQ(closest_point(tree, index, {0, 0, 3.5f}, {INFINITY, true}).side, Side::kOutside);
    EXPECT_EQ(closest_point(tree, index, {0, 0, 0}, {INFINITY, false}).side, Side::kUnknown);
}

}  // namespace
}  // namespace kdrt::test
