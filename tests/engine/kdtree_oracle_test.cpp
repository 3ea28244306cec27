// The kD-tree must give exactly the brute-force answer: same t, triangle, u and v for every ray.

#include <gtest/gtest.h>

#include <tbb/task_arena.h>

#include "kdrt/proto/mesh_io.h"
#include "oracle.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

Mesh load_data_mesh(const char* name) {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/" + name);
    if (!mesh) throw std::runtime_error(mesh.error().to_string());
    return std::move(mesh).value();
}

void check_scene(const Mesh& mesh, const BuildOptions& options, size_t ray_count, uint64_t seed) {
    SCOPED_TRACE(testing::Message() << "seed=" << seed << " (replay with KDRT_TEST_SEED)");
    const KdTree tree = build_kdtree(mesh, options);
    const std::vector<TriVerts> tris = make_tri_verts(mesh);  // the oracle's own copy, by id
    Rng rng(seed);
    const std::vector<Ray> rays = oracle_rays(rng, mesh, tree, ray_count);
    const std::vector<Hit> got = tree_all(tree, rays);
    const std::vector<Hit> want = brute_force_all(tris, rays);
    expect_same_hits(got, want, rays, tris);
    size_t hits = 0;
    for (const Hit& h : want) hits += h.is_hit();
    EXPECT_GT(hits, ray_count / 10) << "the ray set should hit the scene often";
    EXPECT_LT(hits, ray_count) << "the ray set should also miss sometimes";
    // Occlusion agrees with closest hit for every ray, and with the brute-force any-hit loop (on
    // every ray of small scenes, every 50th of big ones: that loop has no filter).
    std::vector<uint8_t> occ(rays.size());
    occluded_single(tree, rays, occ);
    size_t disagree = 0;
    const size_t brute_stride = tris.size() > 2000 ? 25 : 1;
    for (size_t i = 0; i < rays.size(); ++i) {
        const bool brute =
            i % brute_stride == 0 ? brute_force_occluded(tris, rays[i]) : want[i].is_hit();
        if ((occ[i] != 0) != got[i].is_hit() || brute != want[i].is_hit()) {
            if (++disagree <= 5)
                ADD_FAILURE() << "ray " << i << ": occluded=" << int(occ[i]) << " brute=" << brute
                              << " closest hit=" << got[i].is_hit();
        }
    }
    EXPECT_EQ(disagree, 0u);
}

TEST(KdOracle, RandomSoupsMatchBruteForce) {
    const uint64_t seed = test_seed();
    for (uint64_t s = seed; s < seed + 3; ++s) {
        Rng rng(s);
        const Mesh mesh = random_soup(rng, 3000 + 2000 * (s - seed));
        check_scene(mesh, {}, scaled(100'000), s * 7 + 1);
    }
}

TEST(KdOracle, BigTrianglesSoupMatchesBruteForce) {
    Rng rng(test_seed() + 11);
    const Mesh mesh = random_soup(rng, 500, 0.9f);  // long triangles straddle many cells
    check_scene(mesh, {}, scaled(100'000), test_seed() + 12);
}

TEST(KdOracle, BunnyMatchesBruteForce) {
    const Mesh mesh = load_data_mesh("bunny00.off");
    ASSERT_EQ(mesh.triangle_count(), 75408u);
    check_scene(mesh, {}, scaled(100'000), test_seed() + 21);
}

TEST(KdOracle, TeapotInStadiumMatchesBruteForce) {
    const Mesh mesh = teapot_in_stadium();
    ASSERT_GT(mesh.triangle_count(), 14000u);
    const KdTree tree = build_kdtree(mesh);
    const std::vector<TriVerts> tris = make_tri_verts(mesh);  // the oracle's own copy, by id
    // Most oracle rays start in the stadium; add rays aimed at the tiny teapot from far away.
    Rng rng(test_seed() + 31);
    std::vector<Ray> rays = oracle_rays(rng, mesh, tree, scaled(60'000));
    for (size_t i = 0; i < scaled(60'000); ++i) {
        const Vec3 o = rng.in_box(Aabb{{-450, -450, -450}, {450, 450, 450}});
        const Vec3 target = Vec3{0.3f, -0.2f, 0.1f} + rng.on_sphere() * 1.1f;
        rays.push_back(make_ray(o, target - o));
    }
    expect_same_hits(tree_all(tree, rays), brute_force_all(tris, rays), rays, tris);
}

TEST(KdOracle, MiddleSplitTreeMatchesBruteForce) {
    Rng rng(test_seed() + 41);
    const Mesh mesh = random_soup(rng, 4000);
    BuildOptions options;
    options.builder = Builder::kMiddle;
    check_scene(mesh, options, scaled(50'000), test_seed() + 42);
}

TEST(KdOracle, ExtremeCostSettingsStayExact) {
    Rng rng(test_seed() + 51);
    const Mesh mesh = random_soup(rng, 3000);
    BuildOptions cheap_isect;
    cheap_isect.intersection_cost = 0.1f;  // few splits, big leaves
    check_scene(mesh, cheap_isect, scaled(30'000), test_seed() + 52);
    BuildOptions deep;
    deep.intersection_cost = 50.0f;  // splits until the depth cap
    deep.empty_bonus = 0.9f;
    check_scene(mesh, deep, scaled(30'000), test_seed() + 53);
    BuildOptions shallow;
    shallow.max_depth = 3;
    check_scene(mesh, shallow, scaled(30'000), test_seed() + 54);
}

}  // namespace
}  // namespace kdrt::test

namespace kdrt::test {
namespace {

// The filtered oracle used for big meshes must agree exactly with the plain loop.
TEST(OracleSelfCheck, FilteredBruteForceEqualsPlain) {
    const Mesh mesh = load_data_mesh("bunny00.off");
    const KdTree tree = build_kdtree(mesh);
    const std::vector<TriVerts> tris = make_tri_verts(mesh);  // the oracle's own copy, by id
    Rng rng(test_seed() + 61);
    const std::vector<Ray> rays = oracle_rays(rng, mesh, tree, scaled(2'000));
    const FilteredBruteForce filtered(tris);
    std::vector<Hit> plain(rays.size()), fast(rays.size());
    tbb::parallel_for(size_t{0}, rays.size(), [&](size_t i) {
        plain[i] = brute_force_intersect(tris, rays[i]);
        fast[i] = filtered.intersect(rays[i]);
    });
    expect_same_hits(fast, plain, rays);
}

}  // namespace
}  // namespace kdrt::test
