// The kD-tree must give exactly the brute-force answer: same t, triangle, u and v for every ray.

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <span>
#include <string>

#include <tbb/task_arena.h>

#include "kdrt/proto/mesh_io.h"
#include "kdrt/query.h"
#include "oracle.h"
#include "scenes.h"
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

/// Brute force's closest hit of each ray; `hits` counts the rays that hit.
std::vector<Hit> brute_force_hits(std::span<const TriVerts> tris, std::span<const Ray> rays,
                                  size_t& hits) {
    std::vector<Hit> want(rays.size());
    hits = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
        want[i] = brute_force_intersect(tris, rays[i]);
        hits += want[i].is_hit();
    }
    return want;
}

/// True when `got` (n hits) is not brute force's every-hit list of `ray`, bit for bit.
bool differs_from_brute_force_all(std::span<const TriVerts> tris, const Ray& ray, const Hit* got,
                                  size_t n) {
    const std::vector<Hit> each = brute_force_intersect_all(tris, ray, false);
    return n != each.size() || (n > 0 && std::memcmp(got, each.data(), n * sizeof(Hit)) != 0);
}

/// Rays whose every-hit list in `all` is not brute force's.
size_t all_hits_differences(const AllHits& all, std::span<const TriVerts> tris,
                            std::span<const Ray> rays) {
    size_t differ = 0;
    for (size_t i = 0; i < rays.size(); ++i)
        differ += differs_from_brute_force_all(tris, rays[i], &all.hits[all.offsets[i]],
                                               all.offsets[i + 1] - all.offsets[i]);
    return differ;
}

// Leaves of 1 to 13 triangles (one leaf: max_depth 0; a few: max_depth 2) that share a vertex and
// edges, with an exact duplicate (a tie at the same t, broken by the lower id) and a second,
// parallel fan behind the first: the single-ray kernel tests a leaf four triangles a lane in one
// pass (wide_kernel.h intersect4), so every block remainder, ties inside a block and across
// blocks, and the zero-edge retry in some lanes but not others must give brute force's answer,
// t, triangle, u and v bit for bit, on every ISA and mode.
TEST(KdOracle, LeafBlocksMatchBruteForce) {
    const uint64_t seed = test_seed() + 91;
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    Rng rng(seed);
    for (uint32_t n = 1; n <= 13; ++n) {
        SCOPED_TRACE(testing::Message() << "triangles=" << n);
        // A fan around the origin in a random plane: triangle k is (centre, rim k, rim k + 1);
        // from the third triangle on, the last one repeats triangle 0 (a later id, the same
        // triangle), and every other one lies in a parallel fan a little behind.
        const auto unit = [](Vec3 v) { return v * (1.0f / std::sqrt(dot(v, v))); };
        const Vec3 e0 = rng.on_sphere();
        const Vec3 e1 = unit(cross(e0, rng.on_sphere()));
        const Vec3 e2 = cross(e0, e1);
        const Vec3 centre = rng.on_sphere() * 2.0f;
        Mesh mesh;
        std::vector<Vec3> targets;
        const uint32_t fan = n >= 3 ? n - 1 : n;
        for (uint32_t k = 0; k < fan; ++k) {
            const float a0 = 6.2831853f * k / 12.0f, a1 = 6.2831853f * (k + 1) / 12.0f;
            const Vec3 depth = e2 * (k % 2 == 1 ? 0.25f : 0.0f);
            const Vec3 p0 = centre + depth, p1 = p0 + e0 * std::cos(a0) + e1 * std::sin(a0),
                       p2 = p0 + e0 * std::cos(a1) + e1 * std::sin(a1);
            add_triangle(mesh, p0, p1, p2);
            targets.insert(targets.end(), {p0, p1, p2, (p0 + p1) * 0.5f, (p0 + p2) * 0.5f,
                                           (p0 + p1 + p2) * (1.0f / 3.0f)});
        }
        if (n >= 3) add_triangle(mesh, mesh.corner(0, 0), mesh.corner(0, 1), mesh.corner(0, 2));
        ASSERT_EQ(mesh.triangle_count(), n);
        const std::vector<TriVerts> tris = make_tri_verts(mesh);
        std::vector<Ray> rays;
        for (size_t i = 0; i < scaled(3000); ++i) {
            const Vec3 target = targets[rng.below(static_cast<uint32_t>(targets.size()))];
            const Vec3 o = target + rng.on_sphere() * std::pow(10.0f, rng.uniform(0.0f, 3.0f));
            rays.push_back(make_ray(o, target - o));
        }
        size_t hits = 0;
        const std::vector<Hit> want = brute_force_hits(tris, rays, hits);
        EXPECT_GT(hits, rays.size() / 4) << "the rays are aimed at the fan";
        for (int depth : {0, 2}) {
            BuildOptions options;
            options.max_depth = depth;
            const KdTree tree = build_kdtree(mesh, options);
            uint32_t biggest = 0;
            for (const KdNode& node : tree.nodes)
                if (node.is_leaf()) biggest = std::max(biggest, node.prim_count());
            if (depth == 0) {
                ASSERT_EQ(biggest, n) << "one leaf holds every triangle";
            }
            std::vector<Hit> got(rays.size());
            std::vector<uint8_t> occ(rays.size());
            for (Isa isa : supported_isas()) {
                for (TraceMode mode : {TraceMode::kPacket, TraceMode::kAuto, TraceMode::kSingle}) {
                    SCOPED_TRACE(std::string(isa_name(isa)) + "/" +
                                 std::string(trace_mode_name(mode)) +
                                 " max_depth=" + std::to_string(depth));
                    intersect(tree, rays, got, TraceOptions{mode, isa});
                    size_t differ = 0, wrong = 0;
                    for (size_t i = 0; i < rays.size(); ++i)
                        differ += std::memcmp(&got[i], &want[i], sizeof(Hit)) != 0;
                    EXPECT_EQ(differ, 0u) << "closest hits (t, triangle, u, v) unlike brute force";
                    occluded(tree, rays, occ, TraceOptions{mode, isa});
                    for (size_t i = 0; i < rays.size(); ++i)
                        wrong += (occ[i] != 0) != want[i].is_hit();
                    EXPECT_EQ(wrong, 0u) << "occlusion answers unlike brute force";
                    AllHitsOptions all_options{kMaxHitsPerRay, false};
                    all_options.mode = mode;
                    all_options.isa = isa;
                    EXPECT_EQ(
                        all_hits_differences(intersect_all(tree, rays, all_options), tris, rays),
                        0u)
                        << "every-hit lists unlike brute force";
                }
            }
            // The public single-ray entry points (the default ISA's kernel).
            size_t differ = 0;
            for (size_t i = 0; i < rays.size(); ++i) {
                const Hit h = intersect(tree, rays[i]);
                differ += std::memcmp(&h, &want[i], sizeof(Hit)) != 0 ||
                          occluded(tree, rays[i]) != want[i].is_hit();
            }
            EXPECT_EQ(differ, 0u) << "intersect(tree, ray) / occluded(tree, ray)";
            // The single-ray every-hit query (its own traversal, the same leaf test).
            size_t all_differ = 0;
            std::vector<Hit> one;
            for (size_t i = 0; i < rays.size(); ++i) {
                (void)intersect_all(tree, rays[i], false, one);
                all_differ += differs_from_brute_force_all(tris, rays[i], one.data(), one.size());
            }
            EXPECT_EQ(all_differ, 0u) << "intersect_all(tree, ray)";
        }
    }
}

// The filtered oracle used for big meshes must agree exactly with the plain loop.
/// A unit box (12 triangles) at `lo`.
Mesh unit_box(Vec3 lo) {
    Mesh box;
    for (int k = 0; k < 8; ++k)
        add_vertex(box, {lo.x + (k & 1), lo.y + ((k >> 1) & 1), lo.z + ((k >> 2) & 1)});
    const uint32_t faces[12][3] = {{0, 2, 1}, {1, 2, 3}, {4, 5, 6}, {5, 7, 6},
                                   {0, 1, 4}, {1, 5, 4}, {2, 6, 3}, {3, 6, 7},
                                   {0, 4, 2}, {2, 4, 6}, {1, 3, 5}, {3, 7, 5}};
    for (const auto& f : faces) add_indices(box, f[0], f[1], f[2]);
    return box;
}

// Rays from 1e3 to 1e7 away aimed at the corners and edges of a mesh's bounding box (and at its
// vertices): their slab
// distances to the root box round by a few ulps of the origin, far more than the box's padding,
// so an unwidened root clip drops hits the triangle test reports (1,720 of 20,000 rays at a unit
// box did, before the clip took the traversal tolerance). Every ISA and mode, closest hit,
// occlusion and every hit, against plain brute force.
TEST(KdOracle, FarRaysAtBoxCornersAndEdgesMatchBruteForce) {
    const uint64_t seed = test_seed() + 77;
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    Rng rng(seed);
    Mesh sphere = uv_sphere({0.25f, -0.5f, 3.0f}, 0.75f, 12, 24);
    for (const Mesh& mesh : {unit_box({0, 0, 0}), unit_box({-40.0f, 7.5f, 1000.0f}), sphere}) {
        const KdTree tree = build_kdtree(mesh);
        const std::vector<TriVerts> tris = make_tri_verts(mesh);
        // The corners and edges of the mesh's own bounds (not the padded root cell).
        Aabb box;
        for (const TriVerts& t : tris) {
            box.extend({t.v0[0], t.v0[1], t.v0[2]});
            box.extend({t.v1[0], t.v1[1], t.v1[2]});
            box.extend({t.v2[0], t.v2[1], t.v2[2]});
        }
        std::vector<Ray> rays;
        for (size_t i = 0; i < scaled(6000); ++i) {
            // Half at the box's corners and edges, half at the mesh's vertices.
            Vec3 p;
            if (rng.below(2)) {
                for (int a = 0; a < 3; ++a) p[a] = rng.below(2) ? box.hi[a] : box.lo[a];
                if (rng.below(2)) {
                    const int a = static_cast<int>(rng.below(3));
                    p[a] = rng.uniform(box.lo[a], box.hi[a]);
                }
            } else {
                const TriVerts& t = tris[rng.below(static_cast<uint32_t>(tris.size()))];
                p = {t.v0[0], t.v0[1], t.v0[2]};
            }
            const float far = std::pow(10.0f, rng.uniform(3.0f, 7.0f));
            const Vec3 o = p + rng.on_sphere() * far;
            rays.push_back(make_ray(o, p - o));
        }
        size_t hits = 0;
        const std::vector<Hit> want = brute_force_hits(tris, rays, hits);
        EXPECT_GT(hits, rays.size() / 4) << "the rays should often graze the mesh";
        std::vector<Hit> got(rays.size());
        std::vector<uint8_t> occ(rays.size());
        for (Isa isa : supported_isas()) {
            for (TraceMode mode : {TraceMode::kPacket, TraceMode::kAuto, TraceMode::kSingle}) {
                SCOPED_TRACE(std::string(isa_name(isa)) + "/" + std::string(trace_mode_name(mode)));
                intersect(tree, rays, got, TraceOptions{mode, isa});
                expect_same_hits(got, want, rays, tris);
                occluded(tree, rays, occ, TraceOptions{mode, isa});
                size_t wrong = 0;
                for (size_t i = 0; i < rays.size(); ++i) wrong += (occ[i] != 0) != want[i].is_hit();
                EXPECT_EQ(wrong, 0u) << "occlusion answers that differ from brute force";
                AllHitsOptions all_options{kMaxHitsPerRay, false};
                all_options.mode = mode;
                all_options.isa = isa;
                EXPECT_EQ(all_hits_differences(intersect_all(tree, rays, all_options), tris, rays),
                          0u)
                    << "every-hit answers that differ from brute force";
            }
        }
    }
}

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
