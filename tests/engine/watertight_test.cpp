// Watertightness (Woop, Benthin & Wald 2013): rays through shared edges and vertices of a closed
// mesh never slip through.

#include <gtest/gtest.h>

#include <atomic>

#include <tbb/parallel_for.h>

#include "kdrt/trace.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

size_t count_misses(const KdTree& tree, const std::vector<Ray>& rays) {
    std::atomic<size_t> misses{0};
    tbb::parallel_for(size_t{0}, rays.size(), [&](size_t i) {
        if (!intersect(tree, rays[i]).is_hit() || !occluded(tree, rays[i])) misses.fetch_add(1);
    });
    return misses.load();
}

class Watertight : public testing::Test {
protected:
    static void SetUpTestSuite() {
        mesh_ = new Mesh(uv_sphere({0.125f, -0.375f, 0.25f}, 1.0f, 180, 360));
        tree_ = new KdTree(build_kdtree(*mesh_));
    }
    static void TearDownTestSuite() {
        delete tree_;
        delete mesh_;
    }
    static Mesh* mesh_;
    static KdTree* tree_;
};
Mesh* Watertight::mesh_ = nullptr;
KdTree* Watertight::tree_ = nullptr;

TEST_F(Watertight, NoRayFromInsideEscapes) {
    const uint64_t seed = test_seed() + 300;
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    Rng rng(seed);
    const Vec3 c{0.125f, -0.375f, 0.25f};
    std::vector<Ray> rays;
    const size_t n = scaled(1'000'000);
    for (size_t i = 0; i < n; ++i) {
        // Half from the centre (rays through every pole vertex and ring edge), half from anywhere
        // inside.
        const Vec3 o = i % 2 ? c : c + rng.on_sphere() * rng.uniform(0.0f, 0.95f);
        rays.push_back(make_ray(o, rng.on_sphere()));
    }
    EXPECT_EQ(count_misses(*tree_, rays), 0u);
}

TEST_F(Watertight, RaysAtVerticesAndEdgesFromOutsideHit) {
    const uint64_t seed = test_seed() + 301;
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    Rng rng(seed);
    const Vec3 c{0.125f, -0.375f, 0.25f};
    const Mesh& m = *mesh_;
    std::vector<Ray> rays;
    const size_t n = scaled(1'000'000);
    for (size_t i = 0; i < n; ++i) {
        const auto tri = rng.below(static_cast<uint32_t>(m.triangle_count()));
        const int corner = static_cast<int>(rng.below(3));
        const Vec3 a = m.corner(tri, corner), b = m.corner(tri, (corner + 1) % 3);
        const float s = rng.uniform();
        // At a vertex, an edge midpoint, or anywhere along an edge.
        const Vec3 target = i % 3 == 0 ? a : (i % 3 == 1 ? (a + b) * 0.5f : a + (b - a) * s);
        const Vec3 outward = target - c;
        const Vec3 o = c + outward * 3.0f + rng.on_sphere() * 0.5f;
        rays.push_back(make_ray(o, target - o));
    }
    EXPECT_EQ(count_misses(*tree_, rays), 0u);
}

TEST_F(Watertight, AxisAlignedRaysThroughThePoles) {
    // Rays straight along z through the pole vertices, where hundreds of triangles meet.
    const Vec3 c{0.125f, -0.375f, 0.25f};
    for (float sign : {1.0f, -1.0f}) {
        const Hit h = intersect(*tree_, make_ray(c + Vec3{0, 0, -3 * sign}, {0, 0, sign}));
        ASSERT_TRUE(h.is_hit());
        EXPECT_NEAR(h.t, 2.0f, 1e-5f);
        const Hit inside = intersect(*tree_, make_ray(c, {0, 0, sign}));
        ASSERT_TRUE(inside.is_hit());
        EXPECT_NEAR(inside.t, 1.0f, 1e-5f);
    }
}

}  // namespace
}  // namespace kdrt::test
