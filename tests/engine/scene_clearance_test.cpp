// HitClearance (kdrt/hit_clearance.h, engine/src/scene_clearance.h): a single merged return skips
// its every-hit window only where the closest hit is provably the first merged hit. Held to the
// every-hit oracle.

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <memory>
#include <string>

#include "kdrt/hit_clearance.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/query.h"
#include "kdrt/scan.h"
#include "kdrt/scene.h"
#include "kdrt/trace.h"
#include "scene_clearance.h"
#include "scenes.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

bool same_bits(const Hit& a, const Hit& b) { return std::memcmp(&a, &b, sizeof a) == 0; }

Mesh load_data_mesh(const char* name) {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/" + name);
    if (!mesh) throw std::runtime_error(mesh.error().message);
    return std::move(*mesh);
}

/// Two triangles sharing the edge (0,0,0)-(1,0,0), the second folded over the first, `lift` above
/// it at (0,1): a ray down through the fold meets both within the merge tolerance.
Mesh folded_pair(float lift) {
    Mesh m;
    add_triangle(m, {0, 0, 0}, {1, 0, 0}, {0, 1, 0});
    add_triangle(m, {0, 0, 0}, {1, 0, 0}, {0, 1, lift});
    return m;
}

struct Counts {
    size_t alone = 0, windowed = 0, not_closest = 0;
};

/// For every ray's closest hit that hit_is_alone passes, the oracle's first merged hit is that
/// closest hit, bit for bit. Returns how many passed, how many did not, and how many closest
/// hits were not the first merged hit.
Counts check(const Mesh& mesh, const std::vector<Ray>& rays) {
    const KdTree tree = build_kdtree(mesh);
    const HitClearance clear = build_hit_clearance(tree);
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    EXPECT_EQ(clear.size(), tris.size());
    Counts c;
    for (size_t i = 0; i < rays.size(); ++i) {
        const Hit first = intersect(tree, rays[i]);
        if (!first.is_hit()) continue;
        const std::vector<Hit> want = brute_force_intersect_all(tris, rays[i], true);
        EXPECT_FALSE(want.empty()) << "ray " << i;
        if (want.empty()) continue;
        const bool closest = same_bits(want[0], first);
        c.not_closest += !closest;
        if (detail::hit_is_alone(clear, rays[i], first)) {
            ++c.alone;
            EXPECT_TRUE(closest) << "ray " << i << ": alone, but the first merged hit is prim "
                                 << want[0].prim << " at t " << want[0].t << ", not prim "
                                 << first.prim << " at t " << first.t;
        } else {
            ++c.windowed;
        }
    }
    return c;
}

/// Rays from origins at distance `lo`..`hi` from the mesh's centre `c`, aimed at its triangles:
/// inside, at vertices, at edge midpoints, and a tiny step beside those.
std::vector<Ray> aimed_rays(Rng& rng, const Mesh& mesh, Vec3 c, float lo, float hi, size_t n) {
    std::vector<Ray> rays;
    for (size_t k = 0; k < n; ++k) {
        const auto tri = rng.below(static_cast<uint32_t>(mesh.triangle_count()));
        const Vec3 a = mesh.corner(tri, 0), b = mesh.corner(tri, 1), d = mesh.corner(tri, 2);
        Vec3 target;
        switch (k % 4) {
            case 0: {
                const float u = rng.uniform(), v = rng.uniform() * (1.0f - u);
                target = a + (b - a) * u + (d - a) * v;
                break;
            }
            case 1:
                target = a;
                break;
            case 2:
                target = (a + b) * 0.5f;
                break;
            default:
                target = (a + d) * 0.5f + rng.on_sphere() * 1e-5f;
                break;
        }
        const Vec3 o = c + rng.on_sphere() * rng.uniform(lo, hi);
        rays.push_back(make_ray(o, target - o));
    }
    return rays;
}

TEST(SceneClearance, AloneHitsAreTheFirstMergedHit) {
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    Rng rng(seed + 5);
    // The bunny (a scanned mesh, coordinates up to 0.5), from near and from far (the tolerance
    // grows with the origin's magnitude), and a sphere.
    const Mesh bunny = load_data_mesh("bunny00.off");
    for (const auto& [lo, hi] : {std::pair{0.6f, 1.5f}, std::pair{10.0f, 40.0f}}) {
        const Counts c = check(bunny, aimed_rays(rng, bunny, {0, 0, 0}, lo, hi, scaled(400)));
        EXPECT_GT(c.alone, 0u);
        EXPECT_GT(c.windowed, 0u);
    }
    const Mesh sphere = uv_sphere({0, 0, 0}, 0.5f, 12, 16);
    const Counts s = check(sphere, aimed_rays(rng, sphere, {0, 0, 0}, 0.8f, 3.0f, scaled(2000)));
    EXPECT_GT(s.alone, 0u);
    EXPECT_GT(s.windowed, 0u);
}

TEST(SceneClearance, FoldsAndCopiesAlwaysGetTheirWindow) {
    // A triangle folded over its neighbour (sharing an edge, lifted 1e-5 at its far corner), and
    // a triangle given twice: rays straight down through them meet two triangles within the
    // merge tolerance, so the first merged hit (the lowest prim, both facing one way) is not the
    // closest hit for the rays that meet the fold first. No such triangle is ruled clear.
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    Rng rng(seed + 6);
    Mesh copies;
    add_triangle(copies, {0, 0, 0}, {1, 0, 0}, {0, 1, 0});
    add_triangle(copies, {0, 0, 0}, {1, 0, 0}, {0, 1, 0});
    for (const Mesh& mesh : {folded_pair(1e-5f), copies}) {
        const KdTree tree = build_kdtree(mesh);
        const HitClearance clear = build_hit_clearance(tree);
        for (const detail::ClearanceRecord& r : clear.records())
            for (const auto& plane : r.plane)
                for (const double x : plane) EXPECT_EQ(x, 0.0);
        std::vector<Ray> rays;
        for (size_t k = 0; k < 500; ++k) {
            const float u = rng.uniform(0.05f, 0.6f), v = rng.uniform(0.05f, 0.3f);
            rays.push_back(make_ray({u, v, 5.0f}, {rng.uniform(-1e-3f, 1e-3f), 0.0f, -1.0f}));
        }
        EXPECT_EQ(check(mesh, rays).alone, 0u);
    }
    // The same two triangles with the second one turned to the other side of their edge (a bent,
    // not folded, pair): the rays through the first one's interior are alone again. (A pair
    // folded over by any angle is never ruled clear: the neighbour's shadow on the triangle's
    // plane overlaps it, and that is all the bound looks at.)
    Mesh open;
    add_triangle(open, {0, 0, 0}, {1, 0, 0}, {0, 1, 0});
    add_triangle(open, {0, 0, 0}, {1, 0, 0}, {0, -1, 0.5f});
    std::vector<Ray> rays;
    for (size_t k = 0; k < 200; ++k) {
        const float u = rng.uniform(0.05f, 0.6f), v = rng.uniform(0.05f, 0.3f);
        rays.push_back(make_ray({u, v, 5.0f}, {0.0f, 0.0f, -1.0f}));
    }
    EXPECT_GT(check(open, rays).alone, 0u);
}

TEST(SceneClearance, TheFoldsClosestHitIsNotItsFirstMergedHit) {
    // What the window is for: through the fold, rays meet the lifted triangle (prim 1) first,
    // and the merged answer is prim 0 below it. A skip there would answer prim 1.
    const Mesh mesh = folded_pair(1e-5f);
    std::vector<Ray> rays;
    for (int k = 0; k < 20; ++k)
        rays.push_back(make_ray({0.1f + 0.01f * k, 0.3f, 5.0f}, {0.0f, 0.0f, -1.0f}));
    const Counts c = check(mesh, rays);
    EXPECT_EQ(c.not_closest, rays.size());
    EXPECT_EQ(c.alone, 0u);
}

TEST(SceneClearance, CrowdedVerticesAreNotLookedAt) {
    // A fan of 300 thin triangles around one vertex (a disc): the neighbours at the centre are
    // not looked at (the work stays linear), so those triangles always get their window; the
    // answers stay the oracle's. A fan of 40 is looked at and its hits clear of the edges skip.
    for (const uint32_t count : {300u, 40u}) {
        Mesh fan;
        const float step = 2.0f * 3.14159265f / static_cast<float>(count);
        // The rim's points, the last triangle closing on the first point (no overlap, no gap).
        const auto rim = [&](uint32_t k) {
            const float a = step * static_cast<float>(k % count);
            return Vec3{std::cos(a), std::sin(a), 0.0f};
        };
        for (uint32_t k = 0; k < count; ++k) add_triangle(fan, {0, 0, 0}, rim(k), rim(k + 1));
        const KdTree tree = build_kdtree(fan);
        const HitClearance clear = build_hit_clearance(tree);
        size_t zero = 0;
        for (const detail::ClearanceRecord& r : clear.records())
            zero += r.plane[0][0] == 0.0f && r.plane[0][1] == 0.0f && r.plane[0][3] == 0.0f;
        Rng rng(test_seed() + count);
        std::vector<Ray> rays;
        for (size_t k = 0; k < 300; ++k) {
            const float r = rng.uniform(0.3f, 0.9f), a = rng.uniform(0.0f, 6.28f);
            rays.push_back(make_ray({r * std::cos(a), r * std::sin(a), 2.0f}, {0.0f, 0.0f, -1.0f}));
        }
        const Counts c = check(fan, rays);
        if (count == 300) {
            EXPECT_EQ(zero, clear.size());
            EXPECT_EQ(c.alone, 0u);
        } else {
            EXPECT_EQ(zero, 0u);
            EXPECT_GT(c.alone, 0u);
        }
    }
}

TEST(SceneClearance, InstancesWithAndWithoutItAnswerTheSame) {
    // The engine keeps no clearance of its own: an instance carries it or not. A lidar among
    // overlapping bunnies (one tree, rigid and mirrored poses) answers the same points and
    // geometry ids, bit for bit, with every instance carrying the tree's clearance, with none,
    // and with every other one; a pose update keeps each instance's clearance.
    const Mesh bunny = load_data_mesh("bunny00.off");
    auto tree = std::make_shared<const KdTree>(build_kdtree(bunny));
    const auto clear = std::make_shared<const HitClearance>(build_hit_clearance(*tree));
    EXPECT_EQ(clear->size(), tree->tri_slots.size());
    EXPECT_EQ(clear->bytes(), sizeof(HitClearance) + 52 * clear->records().size());
    std::vector<SceneInstance> bare, carried, mixed;
    for (int i = 0; i < 12; ++i) {
        Affine3x4 t;
        const float a = 0.5236f * static_cast<float>(i);
        t.m[0][0] = t.m[1][1] = std::cos(a);
        t.m[0][1] = -std::sin(a);
        t.m[1][0] = std::sin(a);
        if (i % 3 == 0) t.m[2][2] = -1.0f;  // mirrored
        t.m[0][3] = 0.6f * std::cos(a);
        t.m[1][3] = 0.6f * std::sin(a);
        bare.push_back({tree, t, nullptr, nullptr});
        carried.push_back({tree, t, nullptr, clear});
        mixed.push_back({tree, t, nullptr, i % 2 ? clear : nullptr});
    }
    const Scene without = build_scene(bare), with = build_scene(carried), half = build_scene(mixed);
    LidarSpec lidar;
    lidar.elevation_deg = lidar_elevations(-30, 30, 32);
    lidar.azimuth_steps = 256;
    lidar.pose.m[11] = 0.05;
    const ScenePointCloud want = scan_lidar(without, lidar);
    EXPECT_GT(want.cloud.points.size(), 1000u);
    for (const Scene* scene : {&with, &half}) {
        const ScenePointCloud got = scan_lidar(*scene, lidar);
        ASSERT_EQ(got.cloud.points.size(), want.cloud.points.size());
        EXPECT_EQ(std::memcmp(got.cloud.points.data(), want.cloud.points.data(),
                              want.cloud.points.size() * sizeof(LidarPoint)),
                  0);
        EXPECT_EQ(got.geom, want.geom);
    }
    Affine3x4 moved;
    moved.m[2][3] = 0.01f;
    const Scene next = with.with_transform(3, moved);
    for (uint32_t g = 0; g < next.size(); ++g) EXPECT_EQ(next.instance(g).clearance, clear);
    EXPECT_EQ(half.instance(0).clearance, nullptr);
}

TEST(SceneClearance, OneOfAnotherTreeIsRefused) {
    auto tree = std::make_shared<const KdTree>(build_kdtree(uv_sphere({0, 0, 0}, 1.0f, 6, 8)));
    auto other = std::make_shared<const KdTree>(build_kdtree(uv_sphere({0, 0, 0}, 1.0f, 5, 7)));
    ASSERT_NE(other->tri_slots.size(), tree->tri_slots.size());
    const auto wrong = std::make_shared<const HitClearance>(build_hit_clearance(*other));
    try {
        (void)build_scene(
            {{tree, Affine3x4{}, nullptr, nullptr}, {tree, Affine3x4{}, nullptr, wrong}});
        ADD_FAILURE() << "a clearance of another triangle count was accepted";
    } catch (const SceneError& e) {
        EXPECT_EQ(e.instance_index(), 1u);
        EXPECT_EQ(e.field(), "clearance");
    }
}

}  // namespace
}  // namespace kdrt::test
