// The exact sweep's fast paths (build_sah.cpp), each against the path it stands for: the
// straddlers' clip at the split plane alone against the polygon clip, and the sweep that skips
// blocks of candidates against the full sweep.

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "build_internal.h"
#include "scenes.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

using detail::BinnedParams;
using detail::build_kdtree_with;

bool same_tree(const KdTree& a, const KdTree& b) {
    return a.nodes == b.nodes && a.leaf_refs == b.leaf_refs && a.tri_ids == b.tri_ids;
}

bool same_box(const Aabb& a, const Aabb& b) {
    for (int k = 0; k < 3; ++k)
        if (!(a.lo[k] == b.lo[k]) || !(a.hi[k] == b.hi[k])) return false;
    return true;
}

/// Soup on a grid: many shared positions (ties), a quarter of the triangles flat in an axis
/// plane (planar events, planes through vertices).
Mesh grid_soup(Rng& rng, size_t count, float grid) {
    Mesh m;
    auto snap = [&](Vec3 v) {
        return Vec3{std::round(v.x / grid) * grid, std::round(v.y / grid) * grid,
                    std::round(v.z / grid) * grid};
    };
    for (size_t i = 0; i < count; ++i) {
        const Vec3 c = rng.in_box({{0, 0, 0}, {1, 1, 1}});
        Vec3 v[3];
        for (Vec3& x : v) x = snap(c + rng.on_sphere() * rng.uniform(0.0f, 0.3f));
        if (i % 4 == 0) {
            const int a = static_cast<int>(i / 4 % 3);
            float* coords[3] = {&v[0].x, &v[1].x, &v[2].x};
            for (float* q : coords) q[a] = coords[0][a];
        }
        add_triangle(m, v[0], v[1], v[2]);
    }
    return m;
}

// The sweep skips blocks of candidates whose lower bound (the sweep's own arithmetic on the
// block's smallest probabilities and counts) shows they cannot be chosen, and sweeps the block
// of the lowest bound first. The tree must be the full sweep's, byte for byte: ties between
// positions (grid soups), between axes (the cube-like grid), planar triangles, empty cuts, and
// cost settings whose empty bonus is on, off, or a penalty (empty_scale above 1).
TEST(KdSweep, PrunedSweepBuildsTheFullSweepsTree) {
    Rng rng(test_seed() + 700);
    const std::vector<Mesh> meshes = {
        teapot_in_stadium(), random_soup(rng, 6000, 0.3f), grid_soup(rng, 6000, 1.0f / 8),
        grid_soup(rng, 9000, 1.0f / 256), grid_soup(rng, 3000, 1.0f / 2)};
    std::vector<BuildOptions> settings(4);
    settings[1].intersection_cost = 2.0f;
    settings[1].empty_bonus = 0.5f;
    settings[2].intersection_cost = 0.1f;
    settings[2].empty_bonus = 0.0f;
    settings[3].empty_bonus = -0.25f;
    BinnedParams pruned;
    pruned.exact_below = std::numeric_limits<uint32_t>::max();  // exact from the root
    BinnedParams full = pruned;
    full.prune_sweep = false;
    size_t inner = 0;
    for (size_t m = 0; m < meshes.size(); ++m) {
        for (size_t o = 0; o < settings.size(); ++o) {
            SCOPED_TRACE(testing::Message() << "mesh " << m << ", setting " << o);
            const KdTree want = build_kdtree_with(meshes[m], settings[o], full);
            const KdTree got = build_kdtree_with(meshes[m], settings[o], pruned);
            EXPECT_TRUE(same_tree(got, want));
            EXPECT_EQ(got.stats.max_depth, want.stats.max_depth);
            for (const KdNode& n : got.nodes) inner += n.is_leaf() ? 0 : 1;
        }
    }
    EXPECT_GT(inner, 20'000u);
}

/// One clip case: a triangle and a cell split on `axis` at `pos`.
struct ClipCase {
    TriVerts tri;
    Aabb cell;
    int axis;
    float pos;
};

float lerp(float a, float b, float t) { return a + (b - a) * t; }

/// A random case around a cell of size `size` at offset `offset`: vertices inside the cell, on
/// its planes, just outside or far outside; the split plane through a vertex, an ulp off one, or
/// anywhere; slivers (two vertices an ulp apart, or three in a line); coordinates shared by two
/// or three vertices.
ClipCase random_case(Rng& rng, float offset, float size) {
    ClipCase c;
    for (int k = 0; k < 3; ++k) {
        const float a = offset + size * rng.uniform(-1.0f, 0.0f);
        const float b = offset + size * rng.uniform(0.01f, 1.0f);
        c.cell.lo[k] = a;
        c.cell.hi[k] = b;
    }
    float* v[3] = {c.tri.v0, c.tri.v1, c.tri.v2};
    for (int i = 0; i < 3; ++i) {
        for (int k = 0; k < 3; ++k) {
            const float lo = c.cell.lo[k], hi = c.cell.hi[k];
            switch (rng.below(24)) {
                case 0:
                    v[i][k] = lo;
                    break;
                case 1:
                    v[i][k] = hi;
                    break;
                case 2:  // just outside
                    v[i][k] =
                        rng.below(2) ? std::nextafter(lo, -INFINITY) : std::nextafter(hi, INFINITY);
                    break;
                case 3:  // far outside
                    v[i][k] = lerp(lo, hi, rng.uniform(-2.0f, 3.0f));
                    break;
                default:
                    v[i][k] = lerp(lo, hi, rng.uniform(0.0f, 1.0f));
                    break;
            }
        }
    }
    switch (rng.below(6)) {
        case 0:  // a sliver: two vertices an ulp apart on every axis
            for (int k = 0; k < 3; ++k) v[1][k] = std::nextafter(v[0][k], INFINITY);
            break;
        case 1:  // three vertices in a line
            for (int k = 0; k < 3; ++k) v[2][k] = v[0][k] + (v[1][k] - v[0][k]) * 0.5f;
            break;
        case 2:  // a coordinate shared by two vertices
            v[1][rng.below(3)] = v[0][rng.below(3)];
            break;
        default:
            break;
    }
    c.axis = static_cast<int>(rng.below(3));
    const int k = c.axis;
    switch (rng.below(4)) {
        case 0:  // through a vertex
            c.pos = v[rng.below(3)][k];
            break;
        case 1:  // an ulp off a vertex
            c.pos = std::nextafter(v[rng.below(3)][k], rng.below(2) ? INFINITY : -INFINITY);
            break;
        default:
            c.pos = lerp(c.cell.lo[k], c.cell.hi[k], rng.uniform(0.0f, 1.0f));
            break;
    }
    c.pos = std::clamp(c.pos, c.cell.lo[k], c.cell.hi[k]);
    return c;
}

// The straddlers' clip at the split plane alone (clip_to_children's fast path) must give the
// polygon clip's answers: each child's flag, and its box where the flag is set (float ==, which
// make_event's keys follow: -0 and +0 are one key). Cells from tiny (1e-38, subnormal
// vertices) to huge (1e37), far from the origin, and every kind of vertex random_case makes.
TEST(KdSweep, StraddlerClipIsThePolygonClip) {
    Rng rng(test_seed() + 710);
    const float offsets[] = {0.0f, 0.0f, 1.0f, 1e6f, -3e4f, 1e-30f, 1e30f};
    const float sizes[] = {1.0f, 1e-38f, 1e-3f, 1.0f, 10.0f, 1e-30f, 1e37f};
    size_t cases = 0, fast = 0, fast_on_plane = 0, fast_tiny_or_huge = 0;
    for (size_t s = 0; s < std::size(sizes); ++s) {
        for (size_t n = 0; n < scaled(40'000); ++n) {
            const ClipCase c = random_case(rng, offsets[s], sizes[s]);
            Aabb left = c.cell, right = c.cell;
            left.hi[c.axis] = c.pos;
            right.lo[c.axis] = c.pos;
            bool want_l = false, want_r = false, got_l = false, got_r = false;
            Aabb want_lb{}, want_rb{}, got_lb{}, got_rb{};
            detail::clip_to_children_by_polygon(c.tri, left, right, c.axis, want_l, want_lb, want_r,
                                                want_rb);
            detail::clip_to_children(c.tri, left, right, c.axis, got_l, got_lb, got_r, got_rb);
            ++cases;
            bool l = false, r = false;
            Aabb lb, rb;
            if (detail::clip_straddler_to_children(c.tri, left, right, c.axis, l, lb, r, rb)) {
                ++fast;
                const float* v[3] = {c.tri.v0, c.tri.v1, c.tri.v2};
                for (const float* x : v) fast_on_plane += x[c.axis] == c.pos ? 1 : 0;
                fast_tiny_or_huge += sizes[s] < 1e-20f || sizes[s] > 1e20f ? 1 : 0;
            }
            ASSERT_EQ(got_l, want_l) << "case " << cases;
            ASSERT_EQ(got_r, want_r) << "case " << cases;
            if (want_l) {
                ASSERT_TRUE(same_box(got_lb, want_lb)) << "case " << cases;
            }
            if (want_r) {
                ASSERT_TRUE(same_box(got_rb, want_rb)) << "case " << cases;
            }
        }
    }
    // The fast path must have been taken often, with vertices on the plane and at the extremes.
    EXPECT_GT(fast, cases / 10);
    EXPECT_GT(fast_on_plane, cases / 100);
    EXPECT_GT(fast_tiny_or_huge, cases / 100);
}

}  // namespace
}  // namespace kdrt::test
