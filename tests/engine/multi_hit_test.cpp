// Every hit along a ray (kdrt/query.h): the kD-tree's lists equal the brute-force lists bit for
// bit; merged counts are the true number of surface crossings on closed meshes, rays through
// vertices and edges included; the batch form keeps the nearest max_hits and is the same at any
// thread count.

#include <gtest/gtest.h>

#include <bit>
#include <cstring>

#include <tbb/task_arena.h>

#include "kdrt/camera.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/query.h"
#include "kdrt/trace.h"
#include "packet.h"
#include "scenes.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

Mesh load_data_mesh(const char* name) {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/" + name);
    if (!mesh) throw std::runtime_error(mesh.error().to_string());
    return std::move(mesh).value();
}

bool same_bits(const Hit& a, const Hit& b) { return std::memcmp(&a, &b, sizeof(Hit)) == 0; }

/// Tree lists against brute-force lists for every ray, with and without merging; returns the
/// total number of hits seen (so callers can check the rays hit something).
size_t check_against_brute_force(const KdTree& tree, std::span<const TriVerts> tris,
                                 std::span<const Ray> rays) {
    size_t total = 0, bad = 0;
    std::vector<Hit> got;
    for (size_t i = 0; i < rays.size(); ++i) {
        for (const bool merge : {false, true}) {
            intersect_all(tree, rays[i], merge, got);
            const std::vector<Hit> want = brute_force_intersect_all(tris, rays[i], merge);
            const bool same = got.size() == want.size() &&
                              std::equal(got.begin(), got.end(), want.begin(), same_bits);
            if (!same && ++bad <= 5)
                ADD_FAILURE() << "ray " << i << " merge=" << merge << ": tree has " << got.size()
                              << " hits, brute force " << want.size();
            if (!merge) {
                total += want.size();
                // The first hit is the closest-hit kernel's answer.
                const Hit closest = intersect(tree, rays[i]);
                if (!(want.empty() ? !closest.is_hit() : same_bits(want.front(), closest)) &&
                    ++bad <= 5)
                    ADD_FAILURE() << "ray " << i << ": first of all hits is not the closest hit";
            }
        }
    }
    EXPECT_EQ(bad, 0u);
    return total;
}

TEST(AllHits, RandomSoupsMatchBruteForce) {
    const uint64_t seed = test_seed();
    for (uint64_t s = seed; s < seed + 3; ++s) {
        SCOPED_TRACE(testing::Message() << "seed=" << s);
        Rng rng(s);
        // Big triangles overlap a lot: many hits per ray, and many triangles in several leaves.
        const Mesh mesh = random_soup(rng, 1500, 0.15f + 0.2f * static_cast<float>(s - seed));
        const KdTree tree = build_kdtree(mesh);
        const std::vector<TriVerts> tris = make_tri_verts(mesh);
        const std::vector<Ray> rays = oracle_rays(rng, mesh, tree, scaled(3000));
        const size_t total = check_against_brute_force(tree, tris, rays);
        EXPECT_GT(total, rays.size()) << "rays should cross several triangles each";
    }
}

TEST(AllHits, BunnyMatchesBruteForce) {
    const Mesh mesh = load_data_mesh("bunny00.off");
    const KdTree tree = build_kdtree(mesh);
    const std::vector<TriVerts> tris = make_tri_verts(mesh);
    Rng rng(test_seed() + 11);
    const std::vector<Ray> rays = oracle_rays(rng, mesh, tree, scaled(300));
    EXPECT_GT(check_against_brute_force(tree, tris, rays), rays.size());
}

TEST(AllHits, MiddleTreeMatchesBruteForce) {
    Rng rng(test_seed() + 12);
    const Mesh mesh = random_soup(rng, 1000, 0.2f);
    BuildOptions options;
    options.builder = Builder::kMiddle;
    const KdTree tree = build_kdtree(mesh, options);
    const std::vector<Ray> rays = oracle_rays(rng, mesh, tree, scaled(800));
    EXPECT_GT(check_against_brute_force(tree, make_tri_verts(mesh), rays), rays.size());
}

/// The cube [-1, 1]^3, 12 triangles wound outwards, shared vertices.
Mesh cube() { return test::box_mesh(-1, 1); }

/// Vertices, edge midpoints and points along edges of `mesh`: where coincident hits happen.
std::vector<Vec3> vertex_and_edge_points(Rng& rng, const Mesh& mesh, size_t count) {
    std::vector<Vec3> points;
    for (size_t i = 0; i < count; ++i) {
        const auto tri = rng.below(static_cast<uint32_t>(mesh.triangle_count()));
        const int corner = static_cast<int>(rng.below(3));
        const Vec3 a = mesh.corner(tri, corner), b = mesh.corner(tri, (corner + 1) % 3);
        switch (rng.below(3)) {
            case 0:
                points.push_back(a);
                break;
            case 1:
                points.push_back((a + b) * 0.5f);
                break;
            default:
                points.push_back(a + (b - a) * rng.uniform());
                break;
        }
    }
    return points;
}

struct ParityResult {
    size_t wrong_merged = 0;    ///< merged count differs from the true crossing count
    size_t wrong_unmerged = 0;  ///< the plain count does (coincident hits counted twice)
};

/// Rays from `inside` through each point (1 crossing) and from far outside through `inside` and
/// on through the point (2 crossings), against a convex closed mesh.
ParityResult convex_parity(const KdTree& tree, Vec3 inside, std::span<const Vec3> points) {
    ParityResult r;
    std::vector<Hit> hits;
    for (const Vec3& p : points) {
        const Vec3 d = p - inside;
        const Ray from_inside = make_ray(inside, d);
        const Ray through = make_ray(inside - d * 3.0f, d);
        for (const auto& [ray, want] : {std::pair{from_inside, 1u}, std::pair{through, 2u}}) {
            if (intersect_all(tree, ray, true, hits) != want) ++r.wrong_merged;
            if (intersect_all(tree, ray, false, hits) != want) ++r.wrong_unmerged;
        }
    }
    return r;
}

TEST(AllHits, MergedCountIsCrossingCountOnCube) {
    const Mesh mesh = cube();
    const KdTree tree = build_kdtree(mesh);
    Rng rng(test_seed() + 20);
    std::vector<Vec3> points = vertex_and_edge_points(rng, mesh, scaled(4000));
    const ParityResult r = convex_parity(tree, {0.0f, 0.0f, 0.0f}, points);
    EXPECT_EQ(r.wrong_merged, 0u);
    // Without merging a ray through an edge or vertex counts every triangle there: the test
    // must see such rays (otherwise it proves nothing).
    EXPECT_GT(r.wrong_unmerged, points.size() / 4);
    // From an off-centre point too.
    const ParityResult r2 = convex_parity(tree, {0.25f, -0.5f, 0.125f}, points);
    EXPECT_EQ(r2.wrong_merged, 0u);
    EXPECT_GT(r2.wrong_unmerged, 0u);
}

TEST(AllHits, MergedCountIsCrossingCountOnSphere) {
    const Vec3 c{0.125f, -0.375f, 0.25f};
    const Mesh mesh = uv_sphere(c, 1.0f, 40, 80);
    const KdTree tree = build_kdtree(mesh);
    Rng rng(test_seed() + 21);
    const std::vector<Vec3> points = vertex_and_edge_points(rng, mesh, scaled(6000));
    const ParityResult r = convex_parity(tree, c, points);
    EXPECT_EQ(r.wrong_merged, 0u);
    EXPECT_GT(r.wrong_unmerged, 0u);
}

TEST(AllHits, MergedParityOnSeveralClosedMeshes) {
    // Nine spheres on a grid: a ray from a sphere's centre through any vertex or edge point of
    // the scene crosses its own sphere once and others twice each: the merged count is odd.
    const Mesh one = uv_sphere({0, 0, 0}, 1.0f, 16, 32);
    const Mesh mesh = replicate_grid(one, 9);
    const KdTree tree = build_kdtree(mesh);
    Rng rng(test_seed() + 22);
    const std::vector<Vec3> points = vertex_and_edge_points(rng, mesh, scaled(4000));
    size_t even = 0, multi = 0;
    std::vector<Hit> hits;
    for (size_t i = 0; i < points.size(); ++i) {
        // The centre of sphere k: the centroid of its vertices' bounds.
        const uint32_t k = rng.below(9);
        const size_t first = k * one.vertex_count();
        Aabb b;
        for (size_t v = first; v < first + one.vertex_count(); ++v) b.extend(mesh.vertex(v));
        const Vec3 centre = (b.lo + b.hi) * 0.5f;
        const Vec3 d = points[i] - centre;
        if (d == Vec3{0, 0, 0}) continue;
        const uint32_t n = intersect_all(tree, make_ray(centre, d), true, hits);
        even += n % 2 == 0;
        multi += n > 1;
    }
    EXPECT_EQ(even, 0u);
    EXPECT_GT(multi, 0u) << "some rays should cross other spheres too";
}

TEST(AllHits, TouchingRayKeepsEvenParity) {
    // A ray grazing the cube's edge x = y = -1 from outside meets the faces x = -1 and y = -1 at
    // one point, facing opposite ways: two hits (a touch), so the parity says "outside".
    const KdTree tree = build_kdtree(cube());
    std::vector<Hit> hits;
    const Ray edge = make_ray({-2.0f, 0.0f, 0.25f}, {1.0f, -1.0f, 0.0f});
    EXPECT_EQ(intersect_all(tree, edge, true, hits) % 2, 0u);
    // Through the corner (-1, -1, -1) from outside, leaving at once.
    const Ray corner = make_ray({-2.0f, 0.0f, 0.0f}, {1.0f, -1.0f, -1.0f});
    EXPECT_EQ(intersect_all(tree, corner, true, hits) % 2, 0u);
    // The same edge crossed into the cube: one crossing in, one out.
    const Ray into = make_ray({-2.0f, -2.0f, 0.25f}, {1.0f, 1.0f, 0.0f});
    EXPECT_EQ(intersect_all(tree, into, true, hits), 2u);
}

TEST(AllHits, BatchKeepsNearestAndCountsAll) {
    Rng rng(test_seed() + 30);
    const Mesh mesh = random_soup(rng, 3000, 0.3f);
    const KdTree tree = build_kdtree(mesh);
    const std::vector<Ray> rays = oracle_rays(rng, mesh, tree, scaled(5000));
    for (const bool merge : {false, true}) {
        for (const uint32_t max_hits : {0u, 1u, 3u, 1000u}) {
            SCOPED_TRACE(testing::Message() << "merge=" << merge << " max_hits=" << max_hits);
            const AllHits all = intersect_all(tree, rays, AllHitsOptions{max_hits, merge});
            ASSERT_EQ(all.offsets.size(), rays.size() + 1);
            ASSERT_EQ(all.counts.size(), rays.size());
            ASSERT_EQ(all.offsets.back(), all.hits.size());
            std::vector<uint32_t> counts(rays.size());
            count_intersections(tree, rays, merge, counts);
            EXPECT_EQ(counts, all.counts);
            size_t bad = 0, truncated = 0;
            std::vector<Hit> one;
            for (size_t i = 0; i < rays.size(); ++i) {
                const uint32_t n = intersect_all(tree, rays[i], merge, one);
                const size_t keep = std::min<size_t>(n, max_hits);
                truncated += keep < n;
                const bool ok =
                    all.counts[i] == n && all.offsets[i + 1] - all.offsets[i] == keep &&
                    std::equal(one.begin(), one.begin() + static_cast<ptrdiff_t>(keep),
                               all.hits.begin() + static_cast<ptrdiff_t>(all.offsets[i]),
                               same_bits);
                if (!ok && ++bad <= 5) ADD_FAILURE() << "ray " << i;
            }
            EXPECT_EQ(bad, 0u);
            if (max_hits < 1000) {
                EXPECT_GT(truncated, 0u);
            }
        }
    }
}

TEST(AllHits, SameAtAnyThreadCount) {
    Rng rng(test_seed() + 31);
    const Mesh mesh = random_soup(rng, 3000, 0.3f);
    const KdTree tree = build_kdtree(mesh);
    const std::vector<Ray> rays = oracle_rays(rng, mesh, tree, scaled(20000));
    auto run = [&](int threads) {
        tbb::task_arena arena(threads);
        return arena.execute([&] { return intersect_all(tree, rays, AllHitsOptions{5, true}); });
    };
    const AllHits a = run(1), b = run(2);
    EXPECT_EQ(a.offsets, b.offsets);
    EXPECT_EQ(a.counts, b.counts);
    ASSERT_EQ(a.hits.size(), b.hits.size());
    EXPECT_EQ(std::memcmp(a.hits.data(), b.hits.data(), a.hits.size() * sizeof(Hit)), 0);
}

/// Camera rays (coherent: the packet path), the oracle's mixed bag, rays through the mesh's
/// vertices and edges (coincident hits), and invalid rays sprinkled in.
std::vector<Ray> packet_test_rays(Rng& rng, const Mesh& mesh, const KdTree& tree, size_t count,
                                  uint32_t res = 48) {
    std::vector<Ray> rays;
    const Camera cam(default_camera(tree.bounds, 1.0f), res, res);
    for (uint32_t y = 0; y < res; ++y)
        for (uint32_t x = 0; x < res; ++x) rays.push_back(cam.ray(x + 0.5f, y + 0.5f));
    const std::vector<Ray> bag = oracle_rays(rng, mesh, tree, count);
    rays.insert(rays.end(), bag.begin(), bag.end());
    const Vec3 from = tree.bounds.lo - tree.bounds.extent();
    for (const Vec3& p : vertex_and_edge_points(rng, mesh, count / 4))
        rays.push_back(make_ray(from, p - from));
    for (size_t i = 0; i < rays.size(); i += 89) {
        rays[i].dx = (i % 2) ? NAN : 0.0f;
        if (i % 2 == 0) rays[i].dy = rays[i].dz = 0.0f;
    }
    return rays;
}

enum class Truth { kBruteForce, kScalarKernel };

/// The batch every-hit answers of every ISA and mode (packets, single rays, auto) equal the
/// brute-force lists (or, on big meshes, the single-ray scalar kernel's, which the tests above
/// hold to brute force) bit for bit, merged or not, counts included, for rays with more raw hits
/// than a packet lane keeps (the overflow path) too.
void check_every_isa_and_mode(const Mesh& mesh, std::span<const Ray> rays, Truth truth,
                              bool want_overflow) {
    const KdTree tree = build_kdtree(mesh);
    const std::vector<TriVerts> tris = make_tri_verts(mesh);
    for (const bool merge : {false, true}) {
        std::vector<std::vector<Hit>> want(rays.size());
        uint32_t most = 0;
        for (size_t i = 0; i < rays.size(); ++i) {
            if (truth == Truth::kBruteForce)
                want[i] = brute_force_intersect_all(tris, rays[i], merge);
            else
                intersect_all(tree, rays[i], merge, want[i]);
            most = std::max(most, static_cast<uint32_t>(want[i].size()));
        }
        if (want_overflow && !merge) {
            EXPECT_GT(most, detail::kPacketHitCapacity) << "no ray takes the overflow path";
        }
        for (Isa isa : supported_isas()) {
            for (TraceMode mode : {TraceMode::kPacket, TraceMode::kAuto, TraceMode::kSingle}) {
                SCOPED_TRACE(testing::Message() << "isa=" << isa_name(isa) << " mode="
                                                << trace_mode_name(mode) << " merge=" << merge);
                AllHitsOptions options;
                options.max_hits = kMaxHitsPerRay;
                options.merge_coincident = merge;
                options.mode = mode;
                options.isa = isa;
                const AllHits got = intersect_all(tree, rays, options);
                std::vector<uint32_t> counts(rays.size());
                count_intersections(tree, rays, options, counts);
                size_t bad = 0;
                for (size_t i = 0; i < rays.size(); ++i) {
                    const size_t n = got.offsets[i + 1] - got.offsets[i];
                    const bool same =
                        n == want[i].size() && got.counts[i] == n && counts[i] == n &&
                        std::equal(want[i].begin(), want[i].end(),
                                   got.hits.begin() + static_cast<ptrdiff_t>(got.offsets[i]),
                                   same_bits);
                    if (!same && ++bad <= 3)
                        ADD_FAILURE()
                            << "ray " << i << ": " << n << " hits (count " << got.counts[i]
                            << ", counted " << counts[i] << "), brute force " << want[i].size();
                }
                EXPECT_EQ(bad, 0u);
            }
        }
    }
}

TEST(AllHits, EveryIsaAndModeEqualsTheScalarKernelOnTheBunny) {
    const Mesh mesh = load_data_mesh("bunny00.off");
    const KdTree tree = build_kdtree(mesh);
    Rng rng(test_seed() + 41);
    check_every_isa_and_mode(mesh, packet_test_rays(rng, mesh, tree, scaled(2000)),
                             Truth::kScalarKernel, false);
}

TEST(AllHits, EveryIsaAndModeEqualsBruteForceOnADenseSoup) {
    Rng rng(test_seed() + 42);
    // Big overlapping triangles: rays with more hits than a packet lane holds.
    const Mesh mesh = random_soup(rng, 4000, 0.6f);
    const KdTree tree = build_kdtree(mesh);
    check_every_isa_and_mode(mesh, packet_test_rays(rng, mesh, tree, scaled(600), 24),
                             Truth::kBruteForce, true);
}

TEST(AllHits, EveryIsaAndModeKeepsParityOnClosedMeshes) {
    Rng rng(test_seed() + 43);
    for (const Mesh& mesh : {cube(), uv_sphere({0.2f, -0.1f, 0.3f}, 1.5f, 24, 48)}) {
        const KdTree tree = build_kdtree(mesh);
        check_every_isa_and_mode(mesh, packet_test_rays(rng, mesh, tree, scaled(1500)),
                                 Truth::kBruteForce, false);
    }
}

TEST(AllHits, InvalidRaysHaveNoHits) {
    const KdTree tree = build_kdtree(cube());
    std::vector<Hit> hits;
    const float nan = std::numeric_limits<float>::quiet_NaN();
    const Ray rays[] = {make_ray({nan, 0, 0}, {1, 0, 0}), make_ray({-2, 0, 0}, {0, 0, 0}),
                        make_ray({-2, 0, 0}, {1, 0, 0}, 2.0f, 1.0f),
                        make_ray({-2, 0, 0}, {INFINITY, 0, 0})};
    for (const Ray& r : rays) EXPECT_EQ(intersect_all(tree, r, true, hits), 0u);
    // tmin/tmax bound the hits, inclusive at both ends (as closest hit).
    const Ray window = make_ray({-2, 0.5f, 0.25f}, {1, 0, 0}, 1.0f, 3.0f);
    EXPECT_EQ(intersect_all(tree, window, false, hits), 2u);
    const Ray first_only = make_ray({-2, 0.5f, 0.25f}, {1, 0, 0}, 0.0f, 1.0f);
    EXPECT_EQ(intersect_all(tree, first_only, false, hits), 1u);
}

TEST(HitAttributes, NormalIsUnitRightHandedAndPointOnTheRay) {
    // The cube is wound outwards: every normal points away from the centre.
    const Mesh mesh = cube();
    const KdTree tree = build_kdtree(mesh);
    Rng rng(test_seed() + 40);
    std::vector<Hit> hits;
    size_t checked = 0;
    for (int i = 0; i < 200; ++i) {
        const Ray ray = make_ray(rng.on_sphere() * 3.0f, {1, 0, 0});
        intersect_all(tree, make_ray({ray.ox, ray.oy, ray.oz}, Vec3{-ray.ox, -ray.oy, -ray.oz}),
                      false, hits);
        std::vector<Vec3> normals(hits.size()), points(hits.size());
        hit_attributes(tree, hits, normals, points);
        for (size_t k = 0; k < hits.size(); ++k) {
            const Vec3 n = normals[k], p = points[k];
            EXPECT_EQ(n, triangle_normal(tree.triangle(hits[k].prim)));
            EXPECT_EQ(p, hit_point(tree.triangle(hits[k].prim), hits[k]));
            EXPECT_NEAR(dot(n, n), 1.0f, 1e-6f);
            EXPECT_GT(dot(n, p), 0.0f) << "outward normal";
            // On the cube's surface: one coordinate is +-1.
            const float m = std::max({std::fabs(p.x), std::fabs(p.y), std::fabs(p.z)});
            EXPECT_NEAR(m, 1.0f, 1e-6f);
            const Vec3 o{ray.ox, ray.oy, ray.oz};
            const Vec3 on_ray = o + (o * -1.0f) * hits[k].t;
            const Vec3 d = on_ray - p;
            EXPECT_LT(std::sqrt(dot(d, d)), 1e-5f);
            ++checked;
        }
    }
    EXPECT_GE(checked, 400u);  // two faces per ray through the centre, or more at edges
    EXPECT_EQ(triangle_normal(TriVerts{{0, 0, 0}, {1, 0, 0}, {0, 1, 0}}), (Vec3{0, 0, 1}));
    EXPECT_EQ(triangle_normal(TriVerts{{0, 0, 0}, {0, 1, 0}, {1, 0, 0}}), (Vec3{0, 0, -1}));
    EXPECT_EQ(triangle_normal(TriVerts{{0, 0, 0}, {1, 1, 1}, {2, 2, 2}}), (Vec3{}));
}

}  // namespace
}  // namespace kdrt::test
