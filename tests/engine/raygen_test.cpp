#include "kdrt/raygen.h"

#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include <cmath>
#include <cstring>
#include <numbers>
#include <stdexcept>
#include <string>
#include <vector>

#include "kdrt/camera.h"
#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/trace.h"
#include "test_util.h"

namespace kdrt {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

using test::test_seed;

Vec3 origin(const Ray& r) { return {r.ox, r.oy, r.oz}; }
Vec3 direction(const Ray& r) { return {r.dx, r.dy, r.dz}; }
float length(Vec3 v) { return std::sqrt(dot(v, v)); }

/// A UV sphere of radius 1 at the origin above a 6 x 6 floor at y = -1.5: it casts a shadow,
/// shows front and back faces, and leaves background pixels.
Mesh sphere_on_floor() {
    Mesh mesh;
    constexpr uint32_t kStacks = 24, kSlices = 48;
    for (uint32_t i = 0; i <= kStacks; ++i) {
        const double theta = std::numbers::pi * i / kStacks;
        for (uint32_t j = 0; j < kSlices; ++j) {
            const double phi = 2.0 * std::numbers::pi * j / kSlices;
            mesh.positions.push_back(static_cast<float>(std::sin(theta) * std::cos(phi)));
            mesh.positions.push_back(static_cast<float>(std::cos(theta)));
            mesh.positions.push_back(static_cast<float>(std::sin(theta) * std::sin(phi)));
        }
    }
    for (uint32_t i = 0; i < kStacks; ++i) {
        for (uint32_t j = 0; j < kSlices; ++j) {
            const uint32_t a = i * kSlices + j, b = i * kSlices + (j + 1) % kSlices;
            const uint32_t c = a + kSlices, d = b + kSlices;
            mesh.indices.insert(mesh.indices.end(), {a, c, b, b, c, d});
        }
    }
    const auto base = static_cast<uint32_t>(mesh.vertex_count());
    for (float x : {-3.0f, 3.0f}) {
        for (float z : {-3.0f, 3.0f}) mesh.positions.insert(mesh.positions.end(), {x, -1.5f, z});
    }
    mesh.indices.insert(mesh.indices.end(),
                        {base, base + 1, base + 2, base + 1, base + 3, base + 2});
    return mesh;
}

const KdTree& scene_tree() {
    static const KdTree tree = build_kdtree(sphere_on_floor());
    return tree;
}

std::vector<Ray> generate(RayKind kind, uint32_t res, uint64_t seed) {
    return generate_rays(scene_tree(), RayGenOptions{kind, res, seed});
}

bool same_bytes(const std::vector<Ray>& a, const std::vector<Ray>& b) {
    return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(Ray)) == 0;
}

/// Primary hits of the scene in pixel order, as the secondary ray sets are laid out.
struct PrimaryHit {
    Ray ray;
    Hit hit;
};
std::vector<PrimaryHit> primary_hits(uint32_t res) {
    const std::vector<Ray> rays = generate(RayKind::kPrimary, res, 0);
    std::vector<PrimaryHit> out;
    for (const Ray& r : rays) {
        const Hit h = intersect(scene_tree(), r);
        if (h.is_hit()) out.push_back({r, h});
    }
    return out;
}

/// Unit geometric normal of the hit triangle, on the side the ray came from.
Vec3 facing_normal(const PrimaryHit& p) {
    const TriVerts& t = scene_tree().triangle(p.hit.prim);
    const Vec3 v0{t.v0[0], t.v0[1], t.v0[2]}, v1{t.v1[0], t.v1[1], t.v1[2]},
        v2{t.v2[0], t.v2[1], t.v2[2]};
    Vec3 n = cross(v1 - v0, v2 - v0);
    n = n * (1.0f / length(n));
    return dot(n, direction(p.ray)) > 0.0f ? n * -1.0f : n;
}

bool inside(const Aabb& box, Vec3 p) {
    for (int a = 0; a < 3; ++a) {
        if (!(p[a] >= box.lo[a] && p[a] <= box.hi[a])) return false;
    }
    return true;
}

TEST(RayKindName, RoundTripsEveryKind) {
    for (RayKind kind :
         {RayKind::kPrimary, RayKind::kShadow, RayKind::kDiffuse, RayKind::kRandom}) {
        const auto parsed = parse_ray_kind(ray_kind_name(kind));
        ASSERT_TRUE(parsed.has_value()) << ray_kind_name(kind);
        EXPECT_EQ(*parsed, kind);
    }
    EXPECT_EQ(ray_kind_name(RayKind::kShadow), "shadow");
    EXPECT_FALSE(parse_ray_kind("Primary").has_value());
    EXPECT_FALSE(parse_ray_kind("").has_value());
    EXPECT_FALSE(parse_ray_kind("ambient").has_value());
}

TEST(RayGen, PrimaryRaysAreTheDefaultCameraThroughPixelCentres) {
    constexpr uint32_t kRes = 32;
    const std::vector<Ray> rays = generate(RayKind::kPrimary, kRes, 1);
    ASSERT_EQ(rays.size(), kRes * kRes);
    const Camera camera(default_camera(scene_tree().bounds, 1.0f), kRes, kRes);
    for (uint32_t y = 0; y < kRes; ++y) {
        for (uint32_t x = 0; x < kRes; ++x) {
            const Ray want = camera.ray(x + 0.5f, y + 0.5f);
            ASSERT_EQ(std::memcmp(&rays[y * kRes + x], &want, sizeof(Ray)), 0) << x << "," << y;
        }
    }
    // The sphere is in the middle of the image, the top corners see the background.
    EXPECT_TRUE(intersect(scene_tree(), rays[(kRes / 2) * kRes + kRes / 2]).is_hit());
    EXPECT_FALSE(intersect(scene_tree(), rays[0]).is_hit());
    EXPECT_FALSE(intersect(scene_tree(), rays[kRes - 1]).is_hit());
}

TEST(RayGen, AGivenCameraReplacesTheDefaultForPrimaryAndSecondarySets) {
    constexpr uint32_t kRes = 32;
    const KdTree& tree = scene_tree();
    CameraSpec spec = default_camera(tree.bounds, 1.0f);
    spec.eye = spec.eye + Vec3{0.5f, 0.25f, 0.0f};  // a different view of the same scene
    RayGenOptions options{RayKind::kPrimary, kRes, 1};
    options.camera = spec;
    const std::vector<Ray> rays = generate_rays(tree, options);
    ASSERT_EQ(rays.size(), kRes * kRes);
    const Camera camera(spec, kRes, kRes);
    for (uint32_t y = 0; y < kRes; ++y) {
        for (uint32_t x = 0; x < kRes; ++x) {
            const Ray want = camera.ray(x + 0.5f, y + 0.5f);
            ASSERT_EQ(std::memcmp(&rays[y * kRes + x], &want, sizeof(Ray)), 0) << x << "," << y;
        }
    }
    EXPECT_FALSE(same_bytes(rays, generate(RayKind::kPrimary, kRes, 1)));
    // Shadow and diffuse sets start at this camera's hits: one ray per hit pixel.
    size_t hit_pixels = 0;
    for (const Ray& r : rays) hit_pixels += intersect(tree, r).is_hit() ? 1 : 0;
    ASSERT_GT(hit_pixels, 0u);
    for (RayKind kind : {RayKind::kShadow, RayKind::kDiffuse}) {
        options.kind = kind;
        EXPECT_EQ(generate_rays(tree, options).size(), hit_pixels) << ray_kind_name(kind);
    }
    // Random rays do not use a camera.
    options.kind = RayKind::kRandom;
    EXPECT_TRUE(same_bytes(generate_rays(tree, options), generate(RayKind::kRandom, kRes, 1)));
}

TEST(RayGen, SameSeedGivesIdenticalBytes) {
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    for (RayKind kind :
         {RayKind::kPrimary, RayKind::kShadow, RayKind::kDiffuse, RayKind::kRandom}) {
        SCOPED_TRACE(ray_kind_name(kind));
        const std::vector<Ray> a = generate(kind, 48, seed);
        const std::vector<Ray> b = generate(kind, 48, seed);
        EXPECT_FALSE(a.empty());
        EXPECT_TRUE(same_bytes(a, b));
    }
}

TEST(RayGen, SeedChangesOnlyTheRandomKinds) {
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    EXPECT_TRUE(same_bytes(generate(RayKind::kPrimary, 24, seed),
                           generate(RayKind::kPrimary, 24, seed + 1)));
    EXPECT_TRUE(
        same_bytes(generate(RayKind::kShadow, 24, seed), generate(RayKind::kShadow, 24, seed + 1)));
    EXPECT_FALSE(same_bytes(generate(RayKind::kDiffuse, 24, seed),
                            generate(RayKind::kDiffuse, 24, seed + 1)));
    EXPECT_FALSE(
        same_bytes(generate(RayKind::kRandom, 24, seed), generate(RayKind::kRandom, 24, seed + 1)));
}

TEST(RayGen, IdenticalOnOneAndTwoThreads) {
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    for (RayKind kind :
         {RayKind::kPrimary, RayKind::kShadow, RayKind::kDiffuse, RayKind::kRandom}) {
        SCOPED_TRACE(ray_kind_name(kind));
        std::vector<Ray> one, two;
        tbb::task_arena(1).execute([&] { one = generate(kind, 200, seed); });
        tbb::task_arena(2).execute([&] { two = generate(kind, 200, seed); });
        EXPECT_FALSE(one.empty());
        EXPECT_TRUE(same_bytes(one, two));
    }
}

TEST(RayGen, ShadowRaysLeaveEachHitAndStopBeforeOneLight) {
    constexpr uint32_t kRes = 64;
    const std::vector<PrimaryHit> hits = primary_hits(kRes);
    const std::vector<Ray> rays = generate(RayKind::kShadow, kRes, 1);
    ASSERT_EQ(rays.size(), hits.size());
    ASSERT_FALSE(rays.empty());
    const Aabb& box = scene_tree().bounds;
    const Vec3 ext = box.extent();
    const float diag = length(ext);
    // All segments aim at one light: extend the first past its end by the 0.1% it stops short.
    const Vec3 light = origin(rays[0]) + direction(rays[0]) * (rays[0].tmax / 0.999f);
    EXPECT_FALSE(inside(box, light));
    EXPECT_GT(light.y, box.hi.y) << "the light is above the scene";
    size_t occluded_count = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
        const Ray& r = rays[i];
        const Vec3 to_light = light - origin(r);
        ASSERT_EQ(r.tmin, 0.0f);
        ASSERT_NEAR(length(direction(r)), 1.0f, 1e-6f);
        ASSERT_LT(r.tmax, length(to_light)) << "ray " << i << " reaches the light";
        ASSERT_GT(r.tmax, 0.99f * length(to_light)) << "ray " << i << " stops far before the light";
        ASSERT_GT(dot(direction(r), to_light), 0.9999f * length(to_light)) << "ray " << i;
        // The origin is the primary hit point lifted a tiny distance towards the viewer.
        const PrimaryHit& p = hits[i];
        const Vec3 hit_point = origin(p.ray) + direction(p.ray) * p.hit.t;
        const Vec3 lift = origin(r) - hit_point;
        ASSERT_LT(length(lift), 1e-3f * diag) << "ray " << i;
        ASSERT_GT(dot(lift, facing_normal(p)), 0.0f) << "ray " << i;
        occluded_count += occluded(scene_tree(), r) ? 1 : 0;
    }
    // The sphere shades its own back and shadows the floor; the lit side reaches the light.
    EXPECT_GT(occluded_count, 0u);
    EXPECT_LT(occluded_count, rays.size());
}

TEST(RayGen, DiffuseRaysAreCosineWeightedOnTheViewerSide) {
    constexpr uint32_t kRes = 128;
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    const std::vector<PrimaryHit> hits = primary_hits(kRes);
    const std::vector<Ray> rays = generate(RayKind::kDiffuse, kRes, seed);
    ASSERT_EQ(rays.size(), hits.size());
    ASSERT_GT(rays.size(), 1000u);
    double cos_sum = 0.0;
    size_t self_hits = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
        const Ray& r = rays[i];
        ASSERT_EQ(r.tmin, 0.0f);
        ASSERT_EQ(r.tmax, kInf);
        ASSERT_NEAR(length(direction(r)), 1.0f, 1e-6f);
        const Vec3 n = facing_normal(hits[i]);
        const float cos_theta = dot(direction(r), n);
        ASSERT_GT(cos_theta, 0.0f) << "ray " << i << " points into the surface";
        cos_sum += cos_theta;
        // Leaving a convex sphere or a floor, a diffuse ray never re-hits its own triangle.
        self_hits += intersect(scene_tree(), r).prim == hits[i].hit.prim ? 1 : 0;
    }
    EXPECT_EQ(self_hits, 0u);
    // For a cosine-weighted hemisphere E[cos theta] = 2/3 with variance 1/2 - 4/9 = 1/18; a
    // uniform hemisphere would give 1/2. Allow 5 standard deviations of the mean.
    const double n = static_cast<double>(rays.size());
    EXPECT_NEAR(cos_sum / n, 2.0 / 3.0, 5.0 * std::sqrt(1.0 / 18.0 / n));
}

TEST(RayGen, RandomRaysStartInsideTheBoundsAndPointEverywhere) {
    constexpr uint32_t kRes = 100;
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    const std::vector<Ray> rays = generate(RayKind::kRandom, kRes, seed);
    ASSERT_EQ(rays.size(), kRes * kRes);
    const Aabb& box = scene_tree().bounds;
    double sum[3] = {0, 0, 0};
    double abs_sum[3] = {0, 0, 0};
    for (const Ray& r : rays) {
        ASSERT_TRUE(inside(box, origin(r)));
        ASSERT_EQ(r.tmin, 0.0f);
        ASSERT_EQ(r.tmax, kInf);
        ASSERT_NEAR(length(direction(r)), 1.0f, 1e-6f);
        for (int a = 0; a < 3; ++a) {
            sum[a] += direction(r)[a];
            abs_sum[a] += std::fabs(direction(r)[a]);
        }
    }
    const double n = static_cast<double>(rays.size());
    for (int a = 0; a < 3; ++a) {
        // Uniform on the sphere: each component has mean 0 (sd of the mean 0.0058 here) and
        // mean absolute value 1/2.
        EXPECT_NEAR(sum[a] / n, 0.0, 0.03) << "axis " << a;
        EXPECT_NEAR(abs_sum[a] / n, 0.5, 0.02) << "axis " << a;
    }
}

TEST(RayGen, ZeroResolutionGivesNoRays) {
    for (RayKind kind :
         {RayKind::kPrimary, RayKind::kShadow, RayKind::kDiffuse, RayKind::kRandom}) {
        EXPECT_TRUE(generate(kind, 0, 1).empty()) << ray_kind_name(kind);
    }
}

TEST(RayGen, RejectsResolutionBeyondA32BitCount) {
    try {
        (void)generate(RayKind::kPrimary, 70000, 1);
        ADD_FAILURE() << "no exception";
    } catch (const std::invalid_argument& e) {
        EXPECT_NE(std::string(e.what()).find("res"), std::string::npos) << e.what();
    }
}

TEST(RayGen, EmptyMeshGivesMissingPrimariesAndNoSecondaries) {
    const KdTree empty = build_kdtree(Mesh{});
    const std::vector<Ray> primary = generate_rays(empty, {RayKind::kPrimary, 8, 1});
    ASSERT_EQ(primary.size(), 64u);
    for (const Ray& r : primary) EXPECT_FALSE(intersect(empty, r).is_hit());
    EXPECT_TRUE(generate_rays(empty, {RayKind::kShadow, 8, 1}).empty());
    EXPECT_TRUE(generate_rays(empty, {RayKind::kDiffuse, 8, 1}).empty());
    const std::vector<Ray> random = generate_rays(empty, {RayKind::kRandom, 8, 1});
    ASSERT_EQ(random.size(), 64u);
    for (const Ray& r : random) EXPECT_TRUE(std::isfinite(r.ox) && std::isfinite(r.dx));
}

}  // namespace
}  // namespace kdrt
