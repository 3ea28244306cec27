// The binned top levels of the SAH build (build_binned.cpp): where they hand over to the exact
// sweep, determinism, empty-space cuts, degenerate inputs, and tree quality against the exact
// build. Every tree here is also traced against the brute-force oracle.

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include <tbb/task_arena.h>

#include "build_internal.h"
#include "geometry.h"
#include "kdrt/proto/mesh_io.h"
#include "oracle.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

using detail::BinnedParams;
using detail::build_kdtree_with;

constexpr uint32_t kAllExact = std::numeric_limits<uint32_t>::max();

BinnedParams binned_below(uint32_t exact_below, uint32_t bins = 64) {
    BinnedParams params;
    params.exact_below = exact_below;
    params.bins = bins;
    return params;
}

bool same_tree(const KdTree& a, const KdTree& b) {
    return a.nodes == b.nodes && a.leaf_refs == b.leaf_refs && a.tri_ids == b.tri_ids;
}

/// The tree answers every oracle ray as brute force does.
void expect_traces_like_brute_force(const Mesh& mesh, const KdTree& tree, uint64_t seed,
                                    size_t ray_count = 20'000) {
    SCOPED_TRACE(testing::Message() << "seed=" << seed << " (replay with KDRT_TEST_SEED)");
    Rng rng(seed);
    const std::vector<Ray> rays = oracle_rays(rng, mesh, tree, scaled(ray_count));
    const std::vector<TriVerts> tris = make_tri_verts(mesh);
    expect_same_hits(tree_all(tree, rays), brute_force_all(tris, rays), rays, tris);
}

/// Does some inner node split `axis` exactly at `pos`?
bool has_split(const KdTree& tree, int axis, float pos) {
    for (const KdNode& n : tree.nodes)
        if (!n.is_leaf() && n.axis() == axis && n.split() == pos) return true;
    return false;
}

Mesh load_bunny() {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
    if (!mesh) throw std::runtime_error(mesh.error().to_string());
    return std::move(mesh).value();
}

TEST(KdBinned, NodesBelowTheThresholdAreBuiltExactly) {
    Rng rng(test_seed() + 300);
    const Mesh mesh = random_soup(rng, 3000);
    const KdTree exact = build_kdtree_with(mesh, {}, binned_below(kAllExact));
    // More references than triangles never occur at the root, so a threshold above the triangle
    // count leaves the whole build to the exact sweep ...
    EXPECT_TRUE(same_tree(build_kdtree_with(mesh, {}, binned_below(3001)), exact));
    // ... and one at the triangle count bins the root (and the default build is exact here).
    const KdTree binned = build_kdtree_with(mesh, {}, binned_below(3000));
    EXPECT_FALSE(same_tree(binned, exact)) << "the root split should come from the bins";
    EXPECT_TRUE(same_tree(build_kdtree(mesh), exact));
    expect_traces_like_brute_force(mesh, binned, test_seed() + 301);
    // Binned all the way down to small nodes.
    expect_traces_like_brute_force(mesh, build_kdtree_with(mesh, {}, binned_below(16)),
                                   test_seed() + 302);
}

TEST(KdBinned, SameBytesAtAnyThreadCount) {
    Rng rng(test_seed() + 310);
    // Each mesh is just big enough for the parallel paths it is here for (the test took ~130 s
    // under ASan with a 60,000-triangle soup and a 57,600-triangle stadium, each at both
    // thresholds). The soup's root bins and partitions in parallel chunks (more than
    // kParallelRefs = 2^15 references); at 6144 its nodes below the threshold sort their events
    // and build their children in parallel (4096 triangles or more). The stadium's nearly empty
    // cuts hand its root to the exact sweep at any threshold
    // (NearlyEmptyCutsAreLeftToTheExactSweep), so one threshold covers it: its root then sweeps and
    // partitions each axis in parallel chunks (more than kParallelAxes = 2^15 events per axis: its
    // 32,052 triangles give about 64,000).
    const Mesh soup = random_soup(rng, 40000);
    const Mesh stadium = teapot_in_stadium(1000.0f, 90, 180);
    ASSERT_GT(soup.triangle_count(), size_t{1} << 15);
    ASSERT_GT(2 * stadium.triangle_count(), size_t{1} << 15);  // two events per triangle and axis
    struct Case {
        const Mesh* mesh;
        uint32_t exact_below;
    };
    for (const Case& c : {Case{&soup, 64u}, Case{&soup, 6144u}, Case{&stadium, 64u}}) {
        SCOPED_TRACE(testing::Message()
                     << c.mesh->triangle_count() << " triangles, exact below " << c.exact_below);
        auto build_with = [&](int threads) {
            tbb::task_arena arena(threads);
            return arena.execute(
                [&] { return build_kdtree_with(*c.mesh, {}, binned_below(c.exact_below)); });
        };
        const KdTree one = build_with(1), two = build_with(2), four = build_with(4);
        EXPECT_TRUE(same_tree(one, two));
        EXPECT_TRUE(same_tree(one, four));
    }
}

TEST(KdBinned, EmptySpaceIsCutAtTheGeometry) {
    // A small cluster in one corner of a big closed box: the empty space around the cluster must
    // be cut off by planes exactly at the cluster's bounds, not at the nearest bin boundary. (The
    // binned root's best plane is a nearly empty cut, which hands the node to the exact sweep: the
    // test holds that path to the same planes.)
    Mesh mesh;
    const float lo = -100, hi = 100;
    const Vec3 c[8] = {{lo, lo, lo}, {hi, lo, lo}, {lo, hi, lo}, {hi, hi, lo},
                       {lo, lo, hi}, {hi, lo, hi}, {lo, hi, hi}, {hi, hi, hi}};
    const int faces[6][4] = {{0, 1, 3, 2}, {4, 6, 7, 5}, {0, 4, 5, 1},
                             {2, 3, 7, 6}, {0, 2, 6, 4}, {1, 5, 7, 3}};
    for (const auto& f : faces) {
        add_triangle(mesh, c[f[0]], c[f[1]], c[f[2]]);
        add_triangle(mesh, c[f[0]], c[f[2]], c[f[3]]);
    }
    Rng rng(test_seed() + 320);
    const Mesh cluster = random_soup(rng, 5000, 0.05f);  // in about [0, 1]^3
    for (size_t t = 0; t < cluster.triangle_count(); ++t)
        add_triangle(mesh, cluster.corner(t, 0) + Vec3{30, 40, 50},
                     cluster.corner(t, 1) + Vec3{30, 40, 50},
                     cluster.corner(t, 2) + Vec3{30, 40, 50});
    Aabb box;
    for (size_t t = 12; t < mesh.triangle_count(); ++t)
        for (int k = 0; k < 3; ++k) box.extend(mesh.corner(t, k));

    const KdTree binned = build_kdtree_with(mesh, {}, binned_below(64, 32));
    for (int a = 0; a < 3; ++a) {
        EXPECT_TRUE(has_split(binned, a, box.lo[a])) << "axis " << a << " at " << box.lo[a];
        EXPECT_TRUE(has_split(binned, a, box.hi[a])) << "axis " << a << " at " << box.hi[a];
    }
    const KdTree exact = build_kdtree_with(mesh, {}, binned_below(kAllExact));
    EXPECT_LE(binned.stats.sah_cost, 1.05 * exact.stats.sah_cost);
    expect_traces_like_brute_force(mesh, binned, test_seed() + 321);
}

TEST(KdBinned, NearlyEmptyCutsAreLeftToTheExactSweep) {
    // The teapot in a stadium: the sphere fills one or two of the root's bins per axis, so the
    // best binned plane cuts off the empty space around it (only wall pieces on the far side),
    // where the exact sweep splits the sphere itself. The node goes to the exact sweep instead,
    // so the whole tree is the exact one (the stadium's shadow rays did 34% more triangle tests
    // in the binned tree).
    const Mesh stadium = teapot_in_stadium();
    const KdTree exact = build_kdtree_with(stadium, {}, binned_below(kAllExact));
    for (uint32_t exact_below : {64u, 4096u}) {
        SCOPED_TRACE(exact_below);
        const KdTree tree = build_kdtree_with(stadium, {}, binned_below(exact_below));
        EXPECT_TRUE(same_tree(tree, exact));
    }
    expect_traces_like_brute_force(stadium, exact, test_seed() + 325);
}

// The binned root is counted, bounded and binned straight from the triangles, its list of
// references made only where a binned split divides it, and the exact sweep takes a whole mesh
// from the triangles (BinnedParams::root_from_triangles). The tree must be the one the list gives,
// byte for byte: with degenerate triangles mixed in (left out by both), a root the exact sweep
// takes whole (the teapot in a stadium: a nearly empty cut; every node exact; no depth), a root
// the bins divide, and meshes big enough to be counted and binned in parallel chunks.
TEST(KdBinned, RootFromTrianglesBuildsTheListsTree) {
    Rng rng(test_seed() + 330);
    std::vector<Mesh> meshes = {teapot_in_stadium(), random_soup(rng, 3000, 0.2f),
                                random_soup(rng, 40'000, 0.05f)};
    for (Mesh& mesh : meshes) {  // degenerate triangles (zero area) at random places among them
        const size_t solid = mesh.triangle_count();
        for (size_t i = 0; i < solid / 50; ++i) {
            const float t = static_cast<float>(i % 7) * 0.1f;
            add_triangle(mesh, {t, t, t}, {t + 1, t + 1, t + 1}, {t + 2, t + 2, t + 2});
        }
        for (size_t i = solid; i < mesh.triangle_count(); ++i) {
            const size_t j = rng.below(static_cast<uint32_t>(solid));
            for (int k = 0; k < 3; ++k) std::swap(mesh.indices[3 * i + k], mesh.indices[3 * j + k]);
        }
    }
    BuildOptions flat;  // no depth: the root is a leaf of the exact sweep
    flat.max_depth = 0;
    size_t divided = 0;
    for (size_t m = 0; m < meshes.size(); ++m) {
        for (const uint32_t exact_below : {0u, 64u, 4096u, kAllExact}) {
            for (const BuildOptions& options : {BuildOptions{}, flat}) {
                SCOPED_TRACE(testing::Message() << "mesh " << m << ", exact below " << exact_below
                                                << ", max depth " << options.max_depth);
                BinnedParams listed = binned_below(exact_below);
                listed.root_from_triangles = false;
                const KdTree want = build_kdtree_with(meshes[m], options, listed);
                const KdTree got = build_kdtree_with(meshes[m], options, binned_below(exact_below));
                EXPECT_TRUE(same_tree(got, want));
                EXPECT_EQ(got.bounds, want.bounds);
                EXPECT_EQ(got.stats.max_depth, want.stats.max_depth);
                const KdTree exact = build_kdtree_with(meshes[m], options, binned_below(kAllExact));
                divided += !same_tree(got, exact);
            }
        }
    }
    EXPECT_GT(divided, 0u);  // some roots were divided by the bins, not all taken whole
    expect_traces_like_brute_force(meshes[0], build_kdtree(meshes[0]), test_seed() + 331, 4000);
}

TEST(KdBinned, AllTrianglesInOnePlane) {
    Mesh mesh;  // a 96x96 grid of triangle pairs in the plane z = 0.5
    const int n = 96;
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) {
            const float x = i / float(n), y = j / float(n), s = 1.0f / n;
            add_triangle(mesh, {x, y, 0.5f}, {x + s, y, 0.5f}, {x + s, y + s, 0.5f});
            add_triangle(mesh, {x, y, 0.5f}, {x + s, y + s, 0.5f}, {x, y + s, 0.5f});
        }
    const KdTree tree = build_kdtree_with(mesh, {}, binned_below(32));
    EXPECT_GT(tree.stats.leaves, 1000u) << "planar triangles must still be split up";
    expect_traces_like_brute_force(mesh, tree, test_seed() + 330);
    Rng rng(test_seed() + 331);
    std::vector<Ray> rays;
    for (int i = 0; i < 5000; ++i) {  // in the plane itself, and straight down onto it
        rays.push_back(make_ray({rng.uniform(), rng.uniform(), 0.5f},
                                {rng.uniform(-1, 1), rng.uniform(-1, 1), 0}));
        rays.push_back(make_ray({rng.uniform(), rng.uniform(), 3.0f}, {0, 0, -1}));
    }
    const std::vector<TriVerts> tris = make_tri_verts(mesh);
    expect_same_hits(tree_all(tree, rays), brute_force_all(tris, rays), rays, tris);
}

TEST(KdBinned, ManyIdenticalTriangles) {
    Mesh mesh;
    Rng rng(test_seed() + 340);
    const Mesh soup = random_soup(rng, 2000);
    for (size_t t = 0; t < soup.triangle_count(); ++t)
        add_triangle(mesh, soup.corner(t, 0), soup.corner(t, 1), soup.corner(t, 2));
    for (int i = 0; i < 8000; ++i)  // above the soup
        add_triangle(mesh, {0.4f, 0.4f, 1.4f}, {0.6f, 0.4f, 1.5f}, {0.5f, 0.6f, 1.6f});
    const KdTree tree = build_kdtree_with(mesh, {}, binned_below(64));
    EXPECT_LE(tree.stats.max_depth, static_cast<uint32_t>(kMaxDepth));
    // The copies cannot be separated: cutting them only duplicates references.
    EXPECT_LT(tree.stats.refs, 4 * mesh.triangle_count()) << "no runaway duplication";
    expect_traces_like_brute_force(mesh, tree, test_seed() + 341);
    const Hit h = intersect(tree, make_ray({0.5f, 0.5f, 3}, {0, 0, -1}));
    ASSERT_TRUE(h.is_hit());
    EXPECT_EQ(h.prim, 2000u) << "ties go to the lowest id";
}

TEST(KdBinned, HugeAndTinyCoordinates) {
    for (const float scale : {1e30f, 1e-30f, 1e-3f}) {
        SCOPED_TRACE(scale);
        Rng rng(test_seed() + 350);
        const Mesh soup = random_soup(rng, 4000);
        Mesh mesh;
        for (size_t t = 0; t < soup.triangle_count(); ++t)
            add_triangle(mesh, soup.corner(t, 0) * scale, soup.corner(t, 1) * scale,
                         soup.corner(t, 2) * scale);
        const KdTree tree = build_kdtree_with(mesh, {}, binned_below(32));
        EXPECT_GT(tree.stats.leaves, 100u);
        expect_traces_like_brute_force(mesh, tree, test_seed() + 351);
    }
}

// Quality: the binned top levels may choose other splits than the exact sweep, but the tree's
// SAH cost stays within 1% of the exact build's with the default parameters, and within 5% when
// binning goes all the way down to nodes of 64 references.
TEST(KdBinned, SahCostStaysCloseToTheExactBuild) {
    Rng rng(test_seed() + 360);
    const Mesh soup = random_soup(rng, 40000);
    const Mesh bunny = load_bunny();
    const Mesh stadium = teapot_in_stadium();
    for (const Mesh* mesh : {&soup, &bunny, &stadium}) {
        const double exact = build_kdtree_with(*mesh, {}, binned_below(kAllExact)).stats.sah_cost;
        const double defaults = build_kdtree_with(*mesh, {}, BinnedParams{}).stats.sah_cost;
        const double deep = build_kdtree_with(*mesh, {}, binned_below(64)).stats.sah_cost;
        SCOPED_TRACE(testing::Message() << mesh->triangle_count() << " triangles: exact " << exact
                                        << ", default " << defaults << ", binned to 64 " << deep);
        EXPECT_LE(defaults, 1.01 * exact);
        EXPECT_LE(deep, 1.05 * exact);
    }
}

TEST(KdBinned, BunnyTracesLikeBruteForceWhenBinnedDeep) {
    const Mesh bunny = load_bunny();
    expect_traces_like_brute_force(bunny, build_kdtree_with(bunny, {}, binned_below(64)),
                                   test_seed() + 370, 50'000);
}

// Around the threshold and the bin-count steps of small nodes: a node of n references is binned
// at exact_below = n and built exactly at n + 1; binned down to single references (exact_below
// 0), every size still traces like brute force.
TEST(KdBinned, ThresholdEdges) {
    for (const uint32_t n : {1u, 2u, 3u, 15u, 16u, 17u, 127u, 128u, 129u, 300u, 1100u}) {
        SCOPED_TRACE(testing::Message() << n << " triangles");
        Rng rng(test_seed() + 380 + n);
        const Mesh mesh = random_soup(rng, n, 0.3f);
        const KdTree exact = build_kdtree_with(mesh, {}, binned_below(kAllExact));
        EXPECT_TRUE(same_tree(build_kdtree_with(mesh, {}, binned_below(n + 1)), exact));
        for (const uint32_t exact_below : {0u, n}) {
            SCOPED_TRACE(testing::Message() << "exact_below " << exact_below);
            const KdTree tree = build_kdtree_with(mesh, {}, binned_below(exact_below));
            EXPECT_LE(tree.stats.sah_cost, 1.10 * exact.stats.sah_cost);
            expect_traces_like_brute_force(mesh, tree, test_seed() + 381 + n, 4000);
        }
    }
}

// A tiny dense cluster in a huge range: the root's bins span 2e30 and the cluster falls into one
// of them; the nodes below must still bin (and split) it correctly.
TEST(KdBinned, TinyClusterInAHugeRange) {
    Rng rng(test_seed() + 390);
    Mesh mesh = random_soup(rng, 6000, 0.05f);
    add_triangle(mesh, {-1e30f, -1e30f, -1e30f}, {1e30f, -1e30f, -1e30f}, {0, 1e30f, -1e30f});
    add_triangle(mesh, {-1e30f, -1e30f, 1e30f}, {1e30f, -1e30f, 1e30f}, {0, 1e30f, 1e30f});
    add_triangle(mesh, {1e30f, 1e30f, 1e30f}, {1e30f, 0, 1e30f}, {1e30f, 1e30f, 0});
    const KdTree tree = build_kdtree_with(mesh, {}, binned_below(64));
    EXPECT_GT(tree.stats.leaves, 500u) << "the cluster must be split up";
    expect_traces_like_brute_force(mesh, tree, test_seed() + 391);
}

// The exact sweep (build_sah.cpp) must pick, at the root, the plane a plain evaluation of every
// candidate picks: each distinct bound of a triangle on each axis, with triangles lying in the
// plane put left, then right; counts from the bounds directly (left: lower bound below the
// plane, right: upper bound above it); ties to the first candidate (axis, position, planar left
// first). Grid-snapped soups share many positions and hold triangles flat in an axis plane; the
// big ones (over 32k events per axis) take the sweep's parallel chunks.
struct RootSplit {
    bool split = false;
    int axis = 0;
    float pos = 0;
};

RootSplit plain_root_split(const Mesh& mesh, const KdTree& tree, const BuildOptions& options) {
    const detail::SahCost cost = detail::SahCost::from(options);
    std::vector<Aabb> boxes;
    for (const TriVerts& t : make_tri_verts(mesh)) {
        Aabb box;
        if (detail::vertex_bounds_in_cell(t, tree.bounds, box)) boxes.push_back(box);
    }
    // make_tri_verts collapses degenerate triangles to a point; the tree leaves them out.
    std::erase_if(boxes, [&](const Aabb& b) { return b.lo == b.hi; });
    const auto n = static_cast<uint32_t>(boxes.size());
    const Aabb& cell = tree.bounds;
    const double inv_area = 1.0 / detail::half_area(cell);
    double best = INFINITY;
    RootSplit result;
    for (int a = 0; a < 3; ++a) {
        if (!(cell.lo[a] < cell.hi[a])) continue;
        std::vector<float> lows, highs, planar, positions;
        for (const Aabb& b : boxes) {
            lows.push_back(b.lo[a]);
            highs.push_back(b.hi[a]);
            if (b.lo[a] == b.hi[a]) planar.push_back(b.lo[a]);
            positions.push_back(b.lo[a]);
            positions.push_back(b.hi[a]);
        }
        for (auto* v : {&lows, &highs, &planar, &positions}) std::sort(v->begin(), v->end());
        positions.erase(std::unique(positions.begin(), positions.end()), positions.end());
        const int a1 = (a + 1) % 3, a2 = (a + 2) % 3;
        const double e1 = double{cell.hi[a1]} - cell.lo[a1], e2 = double{cell.hi[a2]} - cell.lo[a2];
        for (const float p : positions) {
            const auto below =
                static_cast<uint32_t>(std::lower_bound(lows.begin(), lows.end(), p) - lows.begin());
            const auto above = static_cast<uint32_t>(
                highs.end() - std::upper_bound(highs.begin(), highs.end(), p));
            const auto in_plane =
                static_cast<uint32_t>(std::upper_bound(planar.begin(), planar.end(), p) -
                                      std::lower_bound(planar.begin(), planar.end(), p));
            const double pl = (e1 * e2 + (e1 + e2) * (double{p} - cell.lo[a])) * inv_area;
            const double pr = (e1 * e2 + (e1 + e2) * (double{cell.hi[a]} - p)) * inv_area;
            for (const bool planar_left : {true, false}) {
                if (!planar_left && in_plane == 0) continue;
                const uint32_t nl = below + (planar_left ? in_plane : 0);
                const uint32_t nr = above + (planar_left ? 0 : in_plane);
                if (p == cell.lo[a] && nr >= n) continue;
                if (p == cell.hi[a] && nl >= n) continue;
                const double c = cost.split(pl, pr, nl, nr);
                if (c < best) {
                    best = c;
                    result = {true, a, p};
                }
            }
        }
    }
    if (!(best < cost.leaf(n))) result.split = false;
    return result;
}

TEST(KdSweep, RootSplitIsTheBestCandidate) {
    BuildOptions costly;  // other costs: other winners, more splits
    costly.intersection_cost = 2.0f;
    costly.empty_bonus = 0.5f;
    size_t splits = 0, cases = 0;
    for (const uint32_t n : {1u, 2u, 3u, 4u, 5u, 9u, 40u, 400u, 3000u, 17000u}) {
        for (const int kind : {0, 1, 2}) {
            SCOPED_TRACE(testing::Message() << n << " triangles, kind " << kind);
            Rng rng(test_seed() + 410 + 3 * n + kind);
            const Mesh mesh = kind == 0   ? random_soup(rng, n, 0.3f)
                              : kind == 1 ? snapped_soup(rng, n, 1.0f / 8)
                                          : snapped_soup(rng, n, 1.0f / 256);
            for (const BuildOptions& options : {BuildOptions{}, costly}) {
                // Only the root's split is compared, so the children are made leaves (max_depth
                // 1 enters no cost: the root is chosen as in a full build, which took most of
                // this test's ~55 s under ASan).
                BuildOptions root_only = options;
                root_only.max_depth = 1;
                const KdTree tree = build_kdtree_with(mesh, root_only, binned_below(kAllExact));
                const RootSplit want = plain_root_split(mesh, tree, options);
                const KdNode& root = tree.nodes[0];
                ASSERT_EQ(!root.is_leaf(), want.split);
                if (want.split) {
                    EXPECT_EQ(root.axis(), want.axis);
                    EXPECT_EQ(root.split(), want.pos);
                    ++splits;
                }
                ++cases;
            }
        }
    }
    EXPECT_GT(splits, cases / 2) << "most roots must split";
}

// A cut of empty space hands the node's event lists to its non-empty child as they are
// (BinnedParams::empty_cuts_in_place): the tree must be the one that classifying and copying them
// gives, byte for byte, with empty children on either side, planar triangles on the cut planes
// (grid-snapped soups), and the bigger nodes that build their children concurrently.
TEST(KdSweep, EmptyCutsHandTheirEventsDownAsTheyAre) {
    BuildOptions costly;  // a bigger empty bonus: more empty cuts
    costly.intersection_cost = 2.0f;
    costly.empty_bonus = 0.5f;
    Rng rng(test_seed() + 440);
    const std::vector<Mesh> meshes = {teapot_in_stadium(), random_soup(rng, 3000, 0.3f),
                                      snapped_soup(rng, 3000, 1.0f / 8),
                                      snapped_soup(rng, 9000, 1.0f / 256)};
    size_t empty_left = 0, empty_right = 0;
    for (size_t m = 0; m < meshes.size(); ++m) {
        for (const BuildOptions& options : {BuildOptions{}, costly}) {
            SCOPED_TRACE(testing::Message()
                         << "mesh " << m << ", c_isect " << options.intersection_cost);
            BinnedParams copied = binned_below(kAllExact);
            copied.empty_cuts_in_place = false;
            const KdTree want = build_kdtree_with(meshes[m], options, copied);
            const KdTree got = build_kdtree_with(meshes[m], options, binned_below(kAllExact));
            EXPECT_TRUE(same_tree(got, want));
            EXPECT_EQ(got.stats.max_depth, want.stats.max_depth);
            for (const KdNode& n : got.nodes) {
                if (n.is_leaf()) continue;
                const KdNode& l = got.nodes[n.first_child()];
                const KdNode& r = got.nodes[n.first_child() + 1];
                empty_left +=
                    l.is_leaf() && l.prim_count() == 0 && !(r.is_leaf() && r.prim_count() == 0);
                empty_right +=
                    r.is_leaf() && r.prim_count() == 0 && !(l.is_leaf() && l.prim_count() == 0);
            }
        }
    }
    EXPECT_GT(empty_left, 100u);
    EXPECT_GT(empty_right, 100u);
}

// The passes before the tree (triangle set-up, root cell, root references) run in fixed chunks of
// triangles, in parallel for big meshes. With degenerate triangles scattered over the chunks (far
// outside the others, so that counting one would move the root cell), the tree is the same at
// any thread count, the root cell is the other triangles' bounds, and rays see no degenerate one.
TEST(KdBuild, ChunkedSetUpLeavesDegenerateTrianglesOut) {
    Rng rng(test_seed() + 420);
    Mesh mesh = random_soup(rng, 70'000, 0.1f);
    const size_t solid = mesh.triangle_count();
    for (size_t i = 0; i < 700; ++i) {  // collinear (zero area) at 50..60
        const float t = 50.0f + static_cast<float>(i) / 70.0f;
        add_triangle(mesh, {t, t, t}, {t + 1, t + 1, t + 1}, {t + 2, t + 2, t + 2});
    }
    // Mix them in: swap each degenerate triangle with a random earlier one.
    for (size_t i = solid; i < mesh.triangle_count(); ++i) {
        const size_t j = rng.below(static_cast<uint32_t>(solid));
        for (int k = 0; k < 3; ++k) std::swap(mesh.indices[3 * i + k], mesh.indices[3 * j + k]);
    }
    auto build_with = [&](int threads) {
        tbb::task_arena arena(threads);
        return arena.execute([&] { return build_kdtree(mesh); });
    };
    const KdTree one = build_with(1), two = build_with(2), four = build_with(4);
    EXPECT_TRUE(same_tree(one, two));
    EXPECT_TRUE(same_tree(one, four));
    EXPECT_EQ(one.bounds, two.bounds);
    EXPECT_EQ(one.bounds, four.bounds);
    // Every solid triangle is in some leaf, no degenerate one is (make_tri_verts makes those a
    // point).
    const std::vector<TriVerts> by_id = make_tri_verts(mesh);
    std::vector<uint8_t> referenced(by_id.size(), 0);
    for (const uint32_t ref : one.leaf_refs) {
        const uint32_t id = one.tri_ids[ref & ~KdTree::kLastRef];
        referenced[id] = 1;
        const TriVerts& t = by_id[id];
        ASSERT_FALSE(std::memcmp(t.v0, t.v1, sizeof t.v0) == 0 &&
                     std::memcmp(t.v0, t.v2, sizeof t.v0) == 0)
            << "degenerate triangle " << id << " is in a leaf";
    }
    EXPECT_EQ(std::count(referenced.begin(), referenced.end(), uint8_t{1}),
              static_cast<std::ptrdiff_t>(solid));
    for (int a = 0; a < 3; ++a) {
        EXPECT_GT(one.bounds.lo[a], -0.5f);
        EXPECT_LT(one.bounds.hi[a], 1.5f) << "a degenerate triangle moved the root cell";
    }
    expect_traces_like_brute_force(mesh, one, test_seed() + 421, 4000);
}

// The triangles' leaf order (order_triangles) is made by parallel passes over fixed chunks. It
// must be, at any thread count, what one pass in reference order gives: triangles numbered by
// first reference, then the unreferenced ones by id; the references rewritten to those numbers,
// in the array given (it becomes tree.leaf_refs).
// References are drawn so that a triangle's references often fall in different chunks (and
// threads), in either order, and many triangles are never referenced. The triangles are made
// from the mesh into the buffer given (the build's triangles by id, whose memory tree.tris then
// reuses): every one of its old values is overwritten, a degenerate triangle is its first corner
// three times.
TEST(KdBuild, TriangleLeafOrderIsTheSerialOneAtAnyThreadCount) {
    Rng rng(test_seed() + 430);
    for (const uint32_t n : {0u, 1u, 1000u, 70'000u}) {
        SCOPED_TRACE(n);
        Mesh mesh;
        std::vector<uint8_t> degenerate(n, 0);
        std::vector<TriVerts> by_id(n);
        for (uint32_t id = 0; id < n; ++id) {
            // Vertices shared with the previous triangle now and then, as in a real mesh.
            for (int c = 0; c < 3; ++c) {
                if (id > 0 && c < 2 && rng.below(3) == 0) {
                    mesh.indices.push_back(mesh.indices[3 * (id - 1) + c + 1]);
                    continue;
                }
                mesh.indices.push_back(static_cast<uint32_t>(mesh.vertex_count()));
                for (int a = 0; a < 3; ++a) mesh.positions.push_back(rng.uniform(-1, 1));
            }
            degenerate[id] = rng.below(9) == 0 ? 1 : 0;  // flags are the caller's: any will do
            TriVerts& t = by_id[id];
            for (int a = 0; a < 3; ++a) {
                t.v0[a] = mesh.corner(id, 0)[a];
                t.v1[a] = degenerate[id] ? t.v0[a] : mesh.corner(id, 1)[a];
                t.v2[a] = degenerate[id] ? t.v0[a] : mesh.corner(id, 2)[a];
            }
        }
        std::vector<uint32_t> refs;
        if (n > 0) {
            for (size_t i = 0; i < 2 * size_t{n}; ++i) {
                // Mostly neighbours of the last reference (as leaves are), sometimes anywhere;
                // ids of the top fifth never.
                const uint32_t limit = n - n / 5;
                const uint32_t id = refs.empty() || rng.below(4) == 0
                                        ? rng.below(limit)
                                        : (refs.back() + rng.below(7)) % limit;
                refs.push_back(id);
            }
        }
        // The oracle: one pass in reference order.
        std::vector<uint32_t> slots(n, ~0u), ids, rewritten;
        for (const uint32_t id : refs) {
            if (slots[id] == ~0u) {
                slots[id] = static_cast<uint32_t>(ids.size());
                ids.push_back(id);
            }
            rewritten.push_back(slots[id]);
        }
        for (uint32_t id = 0; id < n; ++id) {
            if (slots[id] != ~0u) continue;
            slots[id] = static_cast<uint32_t>(ids.size());
            ids.push_back(id);
        }
        for (const int threads : {1, 2, 4}) {
            SCOPED_TRACE(threads);
            KdTree tree;
            TreeArray<TriVerts> buffer(n);
            if (n > 0) std::memset(static_cast<void*>(buffer.data()), 0xA5, n * sizeof(TriVerts));
            const TriVerts* const memory = buffer.data();
            TreeArray<uint32_t> given_refs(refs.begin(), refs.end());
            const uint32_t* const refs_memory = given_refs.data();
            tbb::task_arena arena(threads);
            arena.execute([&] {
                detail::order_triangles(tree, std::move(given_refs), mesh, degenerate,
                                        std::move(buffer));
            });
            EXPECT_EQ(tree.tris.data(), memory) << "tree.tris is the buffer given";
            EXPECT_EQ(tree.leaf_refs.data(), refs_memory)
                << "tree.leaf_refs is the references' array, rewritten in place";
            ASSERT_EQ(tree.tri_ids.size(), n);
            EXPECT_TRUE(std::equal(tree.tri_ids.begin(), tree.tri_ids.end(), ids.begin()));
            EXPECT_EQ(tree.tri_slots, slots);
            ASSERT_EQ(tree.leaf_refs.size(), refs.size());
            EXPECT_TRUE(
                std::equal(tree.leaf_refs.begin(), tree.leaf_refs.end(), rewritten.begin()));
            ASSERT_EQ(tree.tris.size(), n);
            for (uint32_t slot = 0; slot < n; ++slot) {
                ASSERT_EQ(std::memcmp(&tree.tris[slot], &by_id[ids[slot]], sizeof(TriVerts)), 0)
                    << slot;
            }
        }
    }
}

// order_triangles writes the mesh's triangles into the buffer it is given: a buffer or degenerate
// flags of another size than the mesh's triangle count are refused with a message naming them.
TEST(KdBuild, TriangleLeafOrderRefusesABufferOfAnotherSize) {
    const Mesh mesh = box_mesh(0.0f, 1.0f);
    const size_t n = mesh.triangle_count();
    const TreeArray<uint32_t> refs{0, 1};
    const std::vector<uint8_t> flags(n, 0), short_flags(n - 1, 0);
    for (const size_t size : {n - 1, n + 1}) {
        KdTree tree;
        try {
            detail::order_triangles(tree, TreeArray<uint32_t>(refs), mesh, flags,
                                    TreeArray<TriVerts>(size));
            ADD_FAILURE() << "a buffer of " << size << " triangles for " << n << " was taken";
        } catch (const std::invalid_argument& e) {
            EXPECT_NE(std::string(e.what()).find("buffer"), std::string::npos) << e.what();
        }
    }
    KdTree tree;
    EXPECT_THROW(detail::order_triangles(tree, TreeArray<uint32_t>(refs), mesh, short_flags,
                                         TreeArray<TriVerts>(n)),
                 std::invalid_argument);
}

// uninitialized_tree_array sizes a tree array without writing it; what is written is read back.
TEST(KdBuild, UninitializedTreeArrayHasItsSize) {
    for (const size_t n : {size_t{0}, size_t{1}, size_t{100'000}}) {
        TreeArray<uint32_t> a = uninitialized_tree_array<uint32_t>(n);
        ASSERT_EQ(a.size(), n);
        ASSERT_EQ(a.capacity(), n);
        for (size_t i = 0; i < n; ++i) a[i] = static_cast<uint32_t>(i * 7);
        for (size_t i = 0; i < n; ++i) ASSERT_EQ(a[i], i * 7);
    }
    // Other constructions still value-initialise.
    TreeArray<uint32_t> zeros(1000);
    EXPECT_EQ(std::count(zeros.begin(), zeros.end(), 0u), 1000);
}

// Grows a random subtree into `slot` of `tree` in the builders' patterns: both children in
// `tree`; the left child in `tree` and the right one apart, then spliced in (the parallel
// branches); both apart (the middle builder). `deferred`: the subtrees built apart go in by
// defer_splice instead of splice. The random draws do not depend on it, so both modes grow the
// same tree. Counts the deferrals made.
void grow_subtree(detail::SubTree& tree, uint32_t slot, int depth, Rng& rng, bool deferred,
                  int& deferrals) {
    auto hand_over = [&](uint32_t at, detail::SubTree& child) {
        if (deferred) {
            detail::defer_splice(tree, at, std::move(child));
            ++deferrals;
        } else {
            detail::splice(tree, at, child);
        }
    };
    const uint32_t kind = depth == 0 ? 0 : rng.below(5);
    if (kind <= 1) {  // a leaf, empty ones included (their first reference is in the bytes too)
        std::vector<uint32_t> prims(rng.below(4));
        for (uint32_t& p : prims) p = rng.below(1000);
        detail::make_leaf(tree, slot, prims);
        tree.max_depth = std::max(tree.max_depth, rng.below(64));
        return;
    }
    const uint32_t first =
        detail::add_child_pair(tree, slot, static_cast<int>(rng.below(3)), rng.uniform());
    if (kind == 2) {  // after a deferral inside the left child, the right one is written here
        grow_subtree(tree, first, depth - 1, rng, deferred, deferrals);
        grow_subtree(tree, first + 1, depth - 1, rng, deferred, deferrals);
    } else if (kind == 3) {
        grow_subtree(tree, first, depth - 1, rng, deferred, deferrals);
        detail::SubTree right;
        grow_subtree(right, 0, depth - 1, rng, deferred, deferrals);
        hand_over(first + 1, right);
    } else {
        detail::SubTree left, right;
        grow_subtree(left, 0, depth - 1, rng, deferred, deferrals);
        grow_subtree(right, 0, depth - 1, rng, deferred, deferrals);
        hand_over(first, left);
        hand_over(first + 1, right);
    }
}

// The parallel builds hand their right subtrees over by defer_splice and copy them into place
// once at the end (flatten_deferred); a write to a tree with deferred subtrees flattens them
// first. Random trees grown both ways must be the same nodes, references and depth, flattened
// serially and in parallel.
TEST(KdBuild, DeferredSplicesGiveWhatSplicesGive) {
    int total_deferrals = 0, still_deferred = 0;
    for (uint64_t round = 0; round < 60; ++round) {
        const uint64_t seed = test_seed() + 500 + round;
        SCOPED_TRACE(testing::Message() << "seed=" << seed);
        const int depth = 2 + static_cast<int>(round % 10);
        detail::SubTree spliced;
        int unused = 0;
        Rng rng_spliced(seed);
        grow_subtree(spliced, 0, depth, rng_spliced, false, unused);
        ASSERT_TRUE(spliced.deferred.empty());
        for (const bool parallel : {false, true}) {
            detail::SubTree tree;
            Rng rng(seed);
            grow_subtree(tree, 0, depth, rng, true, total_deferrals);
            still_deferred += tree.deferred.empty() ? 0 : 1;
            EXPECT_EQ(tree.node_count(), spliced.nodes.size());
            EXPECT_EQ(tree.ref_count(), spliced.refs.size());
            detail::flatten_deferred(tree, parallel);
            EXPECT_TRUE(tree.deferred.empty());
            ASSERT_EQ(tree.nodes.size(), spliced.nodes.size());
            for (size_t i = 0; i < tree.nodes.size(); ++i) {
                ASSERT_EQ(tree.nodes[i].word0(), spliced.nodes[i].word0()) << "node " << i;
                ASSERT_EQ(tree.nodes[i].word1(), spliced.nodes[i].word1()) << "node " << i;
            }
            EXPECT_EQ(tree.refs, spliced.refs);
            EXPECT_EQ(tree.max_depth, spliced.max_depth);
        }
    }
    // The test reaches both paths: subtrees still deferred at the end, and many deferrals.
    EXPECT_GT(still_deferred, 20);
    EXPECT_GT(total_deferrals, 1000);
}

// The exact sweep sorts the straddlers' new events with detail::sort_events (a quicksort with a
// branch-free partition); it must give std::sort's order: every length up to 300 and some long
// ones, random, sorted, reversed, organ-pipe and few distinct keys (the depth limit's case).
TEST(KdSweep, EventSortIsStdSort) {
    Rng rng(test_seed() + 600);
    std::vector<size_t> lengths;
    for (size_t n = 0; n <= 300; ++n) lengths.push_back(n);
    for (const size_t n : {size_t{1000}, size_t{4097}, size_t{20000}}) lengths.push_back(n);
    for (const size_t n : lengths) {
        for (int pattern = 0; pattern < 5; ++pattern) {
            std::vector<uint64_t> keys(n);
            for (size_t i = 0; i < n; ++i) {
                switch (pattern) {
                    case 0:
                        keys[i] = rng.next();
                        break;
                    case 1:
                        keys[i] = i * 3;
                        break;
                    case 2:
                        keys[i] = (n - i) << 32;
                        break;
                    case 3:
                        keys[i] = std::min(i, n - i);
                        break;
                    default:
                        keys[i] = rng.below(3);
                        break;
                }
            }
            std::vector<uint64_t> expected = keys;
            std::sort(expected.begin(), expected.end());
            detail::sort_events(keys.data(), keys.data() + keys.size());
            ASSERT_EQ(keys, expected) << "n=" << n << " pattern=" << pattern;
        }
    }
}

// The binned levels map a reference's six bounds to bins two at a time (BoundsBinMap). Each
// answer must be the scalar BinMap's: random ranges and bin counts, a flat axis (one bin), and
// coordinates at and next to the range's ends and the bin boundaries, inside and outside.
TEST(KdBinned, SixBoundsAtOnceBinAsOneAtATime) {
    Rng rng(test_seed() + 440);
    for (int round = 0; round < 2000; ++round) {
        SCOPED_TRACE(round);
        std::array<detail::BinMap, 3> maps;
        std::array<std::pair<float, float>, 3> ranges;
        for (int a = 0; a < 3; ++a) {
            const float scale = std::ldexp(1.0f, static_cast<int>(rng.below(40)) - 20);
            const float lo = rng.uniform(-1, 1) * scale;
            const float hi = round % 7 == a ? lo : lo + rng.uniform(0, 2) * scale;
            const auto bins = 4 + rng.below(253);
            const double extent = double{hi} - lo;
            maps[a] = extent > 0 ? detail::BinMap{lo, bins / extent, bins} : detail::BinMap{};
            ranges[a] = {lo, hi};
        }
        const detail::BoundsBinMap six(maps);
        auto coordinate = [&](int a) {
            const auto [lo, hi] = ranges[a];
            const double extent = double{hi} - lo;
            switch (rng.below(6)) {
                case 0:
                    return lo;
                case 1:
                    return hi;
                case 2: {  // a bin boundary, or a neighbour of it
                    const uint32_t b = rng.below(maps[a].count + 1);
                    const auto x = static_cast<float>(lo + extent * b / maps[a].count);
                    const int step = static_cast<int>(rng.below(3)) - 1;
                    return step == 0 ? x : std::nextafter(x, step * INFINITY);
                }
                case 3:
                    return lo - rng.uniform(0, 1) * static_cast<float>(extent);  // below
                case 4:
                    return hi + rng.uniform(0, 1) * static_cast<float>(extent);  // above
                default:
                    return lo + rng.uniform() * static_cast<float>(extent);
            }
        };
        std::array<float, 3> lo{}, hi{};
        for (int a = 0; a < 3; ++a) {
            lo[a] = coordinate(a);
            hi[a] = coordinate(a);
        }
        std::array<uint32_t, 6> bins{};
        six(lo, hi, bins);
        for (int a = 0; a < 3; ++a) {
            EXPECT_EQ(bins[detail::BoundsBinMap::kLo[a]], maps[a](lo[a]))
                << "axis " << a << " lo " << lo[a];
            EXPECT_EQ(bins[detail::BoundsBinMap::kHi[a]], maps[a](hi[a]))
                << "axis " << a << " hi " << hi[a];
        }
    }
}

struct ClipCase {
    Aabb cell;
    TriVerts tri;
};

/// A random cell and a random triangle around it (inside, straddling or outside), at `scale`.
ClipCase random_clip_case(Rng& rng, float scale) {
    ClipCase c;
    for (int a = 0; a < 3; ++a) {
        c.cell.lo[a] = rng.uniform(-1, 1) * scale;
        c.cell.hi[a] = c.cell.lo[a] + rng.uniform(0.01f, 2) * scale;
        c.tri.v0[a] = rng.uniform(-2, 2) * scale;
        c.tri.v1[a] = rng.uniform(-2, 2) * scale;
        c.tri.v2[a] = rng.uniform(-2, 2) * scale;
    }
    return c;
}

/// clip_to_children of `tri` against clip_to_cell in each child alone: the same answers and,
/// where a child is reached, the same bounds bit for bit. `*_ok`: clip_to_children's answers.
testing::AssertionResult children_clip_equals_each_alone(const TriVerts& tri, const Aabb& left,
                                                         const Aabb& right, int axis, bool& left_ok,
                                                         bool& right_ok) {
    Aabb left_box, right_box, left_want, right_want;
    detail::clip_to_children(tri, left, right, axis, left_ok, left_box, right_ok, right_box);
    if (left_ok != detail::clip_to_cell(tri, left, left_want))
        return testing::AssertionFailure() << "left answer";
    if (right_ok != detail::clip_to_cell(tri, right, right_want))
        return testing::AssertionFailure() << "right answer";
    if (left_ok && std::memcmp(&left_box, &left_want, sizeof(Aabb)) != 0)
        return testing::AssertionFailure() << "left bounds";
    if (right_ok && std::memcmp(&right_box, &right_want, sizeof(Aabb)) != 0)
        return testing::AssertionFailure() << "right bounds";
    return testing::AssertionSuccess();
}

// The exact phase clips a straddler to both children at once (clip_to_children). It must give,
// bit for bit, what clipping to each child alone gives: random triangles (inside, straddling,
// outside, flat in an axis plane, at 1e6 scale) against random cells and split planes.
TEST(KdClip, BothChildrenAtOnceEqualEachChildAlone) {
    const uint64_t seed = test_seed() + 400;
    SCOPED_TRACE(testing::Message() << "seed=" << seed << " (replay with KDRT_TEST_SEED)");
    Rng rng(seed);
    size_t in_both = 0, in_one = 0, in_none = 0;
    const size_t count = scaled(200'000);
    for (size_t i = 0; i < count; ++i) {
        const float scale = i % 3 == 0 ? 1e6f : 1.0f;
        auto [cell, tri] = random_clip_case(rng, scale);
        if (i % 5 == 0) tri.v1[i % 3] = tri.v2[i % 3] = tri.v0[i % 3];  // flat in an axis plane
        const int axis = static_cast<int>((i / 3) % 3);
        const float pos = cell.lo[axis] + rng.uniform() * (cell.hi[axis] - cell.lo[axis]);
        Aabb left = cell, right = cell;
        left.hi[axis] = pos;
        right.lo[axis] = pos;
        bool left_ok = false, right_ok = false;
        ASSERT_TRUE(children_clip_equals_each_alone(tri, left, right, axis, left_ok, right_ok))
            << "case " << i;
        (left_ok && right_ok ? in_both : left_ok || right_ok ? in_one : in_none) += 1;
    }
    // The cases must reach every outcome, the straddlers most of all.
    EXPECT_GT(in_both, count / 20);
    EXPECT_GT(in_one, count / 20);
    EXPECT_GT(in_none, count / 100);
}

// clip_to_children's one-pass path: a triangle that straddles the split plane and lies inside
// the cell on the other axes (or just past one of the children's other planes, where the path
// must hand over to the full clip), vertices on the plane too (an edge then crosses it for one
// child only). Bit for bit what clipping to each child alone gives.
TEST(KdClip, StraddlersClippedInOnePassEqualEachChildAlone) {
    const uint64_t seed = test_seed() + 440;
    SCOPED_TRACE(testing::Message() << "seed=" << seed << " (replay with KDRT_TEST_SEED)");
    Rng rng(seed);
    size_t in_both = 0;
    const size_t count = scaled(200'000);
    for (size_t i = 0; i < count; ++i) {
        const float scale = i % 3 == 0 ? 1e6f : 1.0f;
        Aabb cell;
        for (int a = 0; a < 3; ++a) {
            cell.lo[a] = rng.uniform(-1, 1) * scale;
            cell.hi[a] = cell.lo[a] + rng.uniform(0.01f, 2) * scale;
        }
        const int axis = static_cast<int>(i % 3);
        const float pos = cell.lo[axis] + rng.uniform(0.1f, 0.9f) * (cell.hi[axis] - cell.lo[axis]);
        Aabb left = cell, right = cell;
        left.hi[axis] = pos;
        right.lo[axis] = pos;
        TriVerts tri;
        float* v[3] = {tri.v0, tri.v1, tri.v2};
        for (int a = 0; a < 3; ++a)
            for (int k = 0; k < 3; ++k)
                v[k][a] = cell.lo[a] + rng.uniform() * (cell.hi[a] - cell.lo[a]);
        // Straddling: one vertex on each side of the plane (the third anywhere in the cell).
        v[0][axis] = std::min(v[0][axis], std::nextafter(pos, -INFINITY));
        v[1][axis] = std::max(v[1][axis], std::nextafter(pos, INFINITY));
        switch ((i / 3) % 8) {
            case 0:  // the third vertex on the plane
                v[2][axis] = pos;
                break;
            case 1:  // a vertex on the plane, one past it (an edge along the plane too)
                v[0][axis] = pos;
                v[2][axis] = pos;
                break;
            case 2: {  // a vertex past another plane of the cell, by an ulp or more
                const int a = static_cast<int>(rng.below(3));
                const bool high = rng.below(2) == 1;
                const float face = high ? cell.hi[a] : cell.lo[a];
                const float past = rng.below(2) == 0
                                       ? std::nextafter(face, high ? INFINITY : -INFINITY)
                                       : face + (high ? 0.25f : -0.25f) * (cell.hi[a] - cell.lo[a]);
                v[rng.below(3)][a] = past;
                break;
            }
            case 3: {  // a vertex on another plane of the cell
                const int a = (axis + 1 + static_cast<int>(rng.below(2))) % 3;
                v[rng.below(3)][a] = rng.below(2) == 1 ? cell.hi[a] : cell.lo[a];
                break;
            }
            default:
                break;
        }
        bool left_ok = false, right_ok = false;
        ASSERT_TRUE(children_clip_equals_each_alone(tri, left, right, axis, left_ok, right_ok))
            << "case " << i;
        in_both += left_ok && right_ok ? 1 : 0;
    }
    EXPECT_GT(in_both, count / 2);  // the straddlers reach both children
}

// The binned phase hands its cut references to the exact sweep with clip_unless_missing: one
// clip where the old hand-over clipped twice (misses_cell, then clip_to_cell). Bit for bit the
// same answer and bounds, on random triangles and on triangles that only touch the cell: a
// vertex on a face, or just outside it (1 to 64 ulps and 2^-22 to 2^-18 of the cell away,
// inside and outside misses_cell's margin), at two scales.
TEST(KdClip, ClipUnlessMissingEqualsMissesCellThenClip) {
    const uint64_t seed = test_seed() + 480;
    SCOPED_TRACE(testing::Message() << "seed=" << seed << " (replay with KDRT_TEST_SEED)");
    Rng rng(seed);
    size_t kept = 0, dropped = 0, touching_kept = 0, touching_dropped = 0;
    const size_t count = scaled(200'000);
    for (size_t i = 0; i < count; ++i) {
        const float scale = i % 3 == 0 ? 1e6f : 1.0f;
        auto [cell, tri] = random_clip_case(rng, scale);
        const bool touching = i % 2 == 1;
        if (touching) {
            // The whole triangle beyond one face of the cell, its nearest vertex on the face or
            // a little beyond it.
            const int a = static_cast<int>((i / 2) % 3);
            const bool high = (i / 6) % 2 == 1;
            const float face = high ? cell.hi[a] : cell.lo[a];
            const float extent = cell.hi[a] - cell.lo[a];
            float gap = 0;
            switch ((i / 12) % 4) {
                case 0:
                    gap = 0;
                    break;
                case 1:
                    gap = std::ldexp(std::fabs(face) + extent, -24) * float(1 + rng.below(64));
                    break;
                case 2:
                    gap = std::ldexp(extent, -22);
                    break;
                default:
                    gap = std::ldexp(extent, -18);
                    break;
            }
            const float sign = high ? 1.0f : -1.0f;
            for (int b = 0; b < 3; ++b) tri.v0[b] = rng.uniform(cell.lo[b], cell.hi[b]);
            tri.v0[a] = face + sign * gap;
            tri.v1[a] = tri.v0[a] + sign * rng.uniform(0, 1) * scale;
            tri.v2[a] = tri.v0[a] + sign * rng.uniform(0, 1) * scale;
            if (i % 5 == 0) tri.v1[a] = tri.v2[a] = tri.v0[a];  // flat in the face's plane
        } else if (i % 5 == 0) {
            tri.v1[i % 3] = tri.v2[i % 3] = tri.v0[i % 3];  // flat in an axis plane
        }
        Aabb want, got;
        const bool want_ok =
            !detail::misses_cell(tri, cell) && detail::clip_to_cell(tri, cell, want);
        const bool got_ok = detail::clip_unless_missing(tri, cell, got);
        ASSERT_EQ(got_ok, want_ok) << "case " << i;
        if (want_ok) {
            ASSERT_EQ(std::memcmp(&got, &want, sizeof(Aabb)), 0) << "case " << i;
        }
        if (touching) {
            (want_ok ? touching_kept : touching_dropped) += 1;
        } else {
            (want_ok ? kept : dropped) += 1;
        }
    }
    // Every outcome is reached, for the touching triangles too.
    EXPECT_GT(kept, count / 20);
    EXPECT_GT(dropped, count / 20);
    EXPECT_GT(touching_kept, count / 100);
    EXPECT_GT(touching_dropped, count / 100);
}

}  // namespace
}  // namespace kdrt::test
