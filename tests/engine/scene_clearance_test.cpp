// HitClearance (engine/src/scene_clearance.h): a single merged return skips its every-hit window
// only where the closest hit is provably the first merged hit. Held to the every-hit oracle.

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <memory>
#include <string>

#include "kdrt/proto/mesh_io.h"
#include "kdrt/query.h"
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
    const detail::HitClearance clear = detail::compute_hit_clearance(tree);
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    EXPECT_EQ(clear.tris.size(), tris.size());
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
        const detail::HitClearance clear = detail::compute_hit_clearance(tree);
        for (const detail::ClearanceRecord& r : clear.tris)
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
        const detail::HitClearance clear = detail::compute_hit_clearance(tree);
        size_t zero = 0;
        for (const detail::ClearanceRecord& r : clear.tris)
            zero += r.plane[0][0] == 0.0f && r.plane[0][1] == 0.0f && r.plane[0][3] == 0.0f;
        Rng rng(test_seed() + count);
        std::vector<Ray> rays;
        for (size_t k = 0; k < 300; ++k) {
            const float r = rng.uniform(0.3f, 0.9f), a = rng.uniform(0.0f, 6.28f);
            rays.push_back(make_ray({r * std::cos(a), r * std::sin(a), 2.0f}, {0.0f, 0.0f, -1.0f}));
        }
        const Counts c = check(fan, rays);
        if (count == 300) {
            EXPECT_EQ(zero, clear.tris.size());
            EXPECT_EQ(c.alone, 0u);
        } else {
            EXPECT_EQ(zero, 0u);
            EXPECT_GT(c.alone, 0u);
        }
    }
}

TEST(SceneClearance, TheCacheKeepsOnePerTree) {
    auto tree = std::make_shared<const KdTree>(build_kdtree(uv_sphere({0, 0, 0}, 1.0f, 6, 8)));
    const auto a = detail::hit_clearance(tree);
    EXPECT_EQ(detail::hit_clearance(tree).get(), a.get());
    EXPECT_EQ(a->tris.size(), tree->tri_slots.size());
    auto other = std::make_shared<const KdTree>(build_kdtree(uv_sphere({0, 0, 0}, 1.0f, 6, 8)));
    EXPECT_NE(detail::hit_clearance(other).get(), a.get());
    // A tree gone, and another one (perhaps at its address): its own clearance, never the old.
    const size_t first_size = a->tris.size();
    tree.reset();
    auto next = std::make_shared<const KdTree>(build_kdtree(uv_sphere({0, 0, 0}, 1.0f, 5, 7)));
    ASSERT_NE(next->tri_slots.size(), first_size);
    EXPECT_EQ(detail::hit_clearance(next)->tris.size(), next->tri_slots.size());
}

}  // namespace
}  // namespace kdrt::test
