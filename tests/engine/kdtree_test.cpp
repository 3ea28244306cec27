// Tree structure, statistics, determinism and degenerate inputs.

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>

#include <tbb/task_arena.h>

#include "kdrt/proto/mesh_io.h"
#include "kdrt/trace.h"
#include "oracle.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

// Akenine-Moeller triangle/box overlap (separating axis theorem) in double.
bool triangle_overlaps_box(const TriVerts& t, const std::array<double, 3>& lo,
                           const std::array<double, 3>& hi) {
    using V = std::array<double, 3>;
    V c, h, v[3];
    for (int a = 0; a < 3; ++a) {
        c[a] = 0.5 * (lo[a] + hi[a]);
        h[a] = 0.5 * (hi[a] - lo[a]);
        v[0][a] = t.v0[a] - c[a];
        v[1][a] = t.v1[a] - c[a];
        v[2][a] = t.v2[a] - c[a];
    }
    auto sub = [](const V& p, const V& q) { return V{p[0] - q[0], p[1] - q[1], p[2] - q[2]}; };
    auto crs = [](const V& p, const V& q) {
        return V{p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]};
    };
    auto dotp = [](const V& p, const V& q) { return p[0] * q[0] + p[1] * q[1] + p[2] * q[2]; };
    auto separated = [&](const V& axis) {
        const double p0 = dotp(v[0], axis), p1 = dotp(v[1], axis), p2 = dotp(v[2], axis);
        const double r =
            h[0] * std::fabs(axis[0]) + h[1] * std::fabs(axis[1]) + h[2] * std::fabs(axis[2]);
        return std::min({p0, p1, p2}) > r || std::max({p0, p1, p2}) < -r;
    };
    const V e[3] = {sub(v[1], v[0]), sub(v[2], v[1]), sub(v[0], v[2])};
    const V unit[3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
    for (const V& u : unit)
        if (separated(u)) return false;
    if (separated(crs(e[0], e[1]))) return false;
    for (const V& u : unit)
        for (const V& ed : e) {
            const V axis = crs(u, ed);
            if (axis[0] != 0 || axis[1] != 0 || axis[2] != 0) {
                if (separated(axis)) return false;
            }
        }
    return true;
}

// Every triangle overlapping the interior of a leaf cell must be referenced by that leaf; refs are
// in range; depth within the cap; cells partition the root (checked by walking them).
void check_tree_properties(const KdTree& tree, const Mesh& mesh) {
    ASSERT_FALSE(tree.nodes.empty());
    for (uint32_t r : tree.leaf_refs) ASSERT_LT(r & ~KdTree::kLastRef, mesh.triangle_count());
    // Each non-empty leaf's run of references is marked last at its end and nowhere else, and no
    // two runs overlap.
    std::vector<uint8_t> covered(tree.leaf_refs.size(), 0);
    size_t runs = 0, marks = 0;
    for (const KdNode& n : tree.nodes) {
        if (!n.is_leaf() || n.prim_count() == 0) continue;
        ++runs;
        ASSERT_LE(uint64_t{n.first_ref()} + n.prim_count(), tree.leaf_refs.size());
        for (uint32_t k = 0; k < n.prim_count(); ++k) {
            ASSERT_FALSE(covered[n.first_ref() + k]) << "runs overlap";
            covered[n.first_ref() + k] = 1;
            ASSERT_EQ((tree.leaf_refs[n.first_ref() + k] & KdTree::kLastRef) != 0,
                      k + 1 == n.prim_count());
        }
    }
    for (uint32_t r : tree.leaf_refs) marks += (r & KdTree::kLastRef) ? 1 : 0;
    EXPECT_EQ(marks, runs);
    // tris is a permutation of the mesh's triangles (leaf order), tri_ids and tri_slots its maps.
    ASSERT_EQ(tree.tri_ids.size(), mesh.triangle_count());
    ASSERT_EQ(tree.tri_slots.size(), mesh.triangle_count());
    const std::vector<TriVerts> by_id = make_tri_verts(mesh);
    for (uint32_t id = 0; id < mesh.triangle_count(); ++id) {
        ASSERT_EQ(tree.tri_ids[tree.tri_slots[id]], id);
        ASSERT_EQ(std::memcmp(&tree.triangle(id), &by_id[id], sizeof(TriVerts)), 0) << id;
    }
    ASSERT_EQ(
        std::memcmp(triangles_by_id(tree).data(), by_id.data(), by_id.size() * sizeof(TriVerts)),
        0);
    // Leaf order: each reference is to a triangle first seen in its own leaf or an earlier one.
    uint32_t seen = 0;
    for (uint32_t ref : tree.leaf_refs) {
        const uint32_t r = ref & ~KdTree::kLastRef;
        ASSERT_LE(r, seen) << "triangles are numbered by first reference";
        if (r == seen) ++seen;
    }
    EXPECT_LE(tree.stats.max_depth, static_cast<uint32_t>(kMaxDepth));
    struct Item {
        uint32_t node;
        Aabb cell;
    };
    std::vector<Item> stack{{0, tree.bounds}};
    double leaf_volume = 0;
    size_t leaves = 0;
    // Per triangle, its bounds (for a cheap rejection before the exact test), once.
    std::vector<std::array<float, 6>> tri_box(mesh.triangle_count());
    for (uint32_t prim = 0; prim < mesh.triangle_count(); ++prim) {
        const TriVerts& t = tree.triangle(prim);
        for (int a = 0; a < 3; ++a) {
            tri_box[prim][a] = std::min({t.v0[a], t.v1[a], t.v2[a]});
            tri_box[prim][3 + a] = std::max({t.v0[a], t.v1[a], t.v2[a]});
        }
    }
    std::vector<uint8_t> in_leaf(mesh.triangle_count(), 0);
    while (!stack.empty()) {
        const Item it = stack.back();
        stack.pop_back();
        const KdNode n = tree.nodes[it.node];
        if (!n.is_leaf()) {
            ASSERT_GT(n.split(), it.cell.lo[n.axis()] - 1e-30f);
            ASSERT_LE(n.split(), it.cell.hi[n.axis()]);
            ASSERT_LT(n.first_child() + 1, tree.nodes.size());
            ASSERT_GT(n.first_child(), it.node) << "children follow their parent (depth-first)";
            Aabb l = it.cell, r = it.cell;
            l.hi[n.axis()] = n.split();
            r.lo[n.axis()] = n.split();
            stack.push_back({n.first_child(), l});
            stack.push_back({n.first_child() + 1, r});
            continue;
        }
        ++leaves;
        const Vec3 e = it.cell.extent();
        leaf_volume += double{e.x} * e.y * e.z;
        for (uint32_t i = 0; i < n.prim_count(); ++i)
            in_leaf[tree.tri_ids[tree.leaf_refs[n.first_ref() + i] & ~KdTree::kLastRef]] = 1;
        struct Unmark {  // in_leaf is all zero again for the next leaf, however this one ends
            std::vector<uint8_t>& in_leaf;
            const KdTree& tree;
            const KdNode& n;
            ~Unmark() {
                for (uint32_t i = 0; i < n.prim_count(); ++i)
                    in_leaf[tree.tri_ids[tree.leaf_refs[n.first_ref() + i] & ~KdTree::kLastRef]] =
                        0;
            }
        } unmark{in_leaf, tree, n};
        std::array<double, 3> lo, hi;
        for (int a = 0; a < 3; ++a) {
            const double shrink = 1e-6 * (double{tree.bounds.hi[a]} - tree.bounds.lo[a]);
            lo[a] = it.cell.lo[a] + shrink;
            hi[a] = it.cell.hi[a] - shrink;
        }
        if (lo[0] >= hi[0] || lo[1] >= hi[1] || lo[2] >= hi[2]) continue;  // flat cell
        for (uint32_t prim = 0; prim < mesh.triangle_count(); ++prim) {
            if (in_leaf[prim]) continue;
            const std::array<float, 6>& b = tri_box[prim];
            bool apart = false;  // cheap bounding-box rejection before the exact test
            for (int a = 0; a < 3; ++a) apart = apart || b[a] > hi[a] || b[3 + a] < lo[a];
            if (apart) continue;
            ASSERT_FALSE(triangle_overlaps_box(tree.triangle(prim), lo, hi))
                << "triangle " << prim << " overlaps leaf " << it.node << " but is not in it";
        }
    }
    EXPECT_EQ(leaves, tree.stats.leaves);
    const Vec3 e = tree.bounds.extent();
    EXPECT_NEAR(leaf_volume, double{e.x} * e.y * e.z, 1e-6 * double{e.x} * e.y * e.z)
        << "leaf cells partition the root";
}

TEST(KdBuild, LeafCellsHoldEveryOverlappingTriangle) {
    Rng rng(test_seed() + 100);
    // O(leaves x triangles): scaled down (not below 300 triangles) under the sanitizers.
    const Mesh mesh = random_soup(rng, std::max<size_t>(300, scaled(1500)), 0.4f);
    check_tree_properties(build_kdtree(mesh), mesh);
    BuildOptions middle;
    middle.builder = Builder::kMiddle;
    check_tree_properties(build_kdtree(mesh, middle), mesh);
}

TEST(KdBuild, SameBytesAtAnyThreadCount) {
    Rng rng(test_seed() + 101);
    const Mesh mesh = random_soup(rng, 40000);
    auto build_with = [&](int threads) {
        tbb::task_arena arena(threads);
        return arena.execute([&] { return build_kdtree(mesh); });
    };
    const KdTree one = build_with(1), two = build_with(2), four = build_with(4);
    ASSERT_EQ(one.nodes.size(), two.nodes.size());
    EXPECT_TRUE(one.nodes == two.nodes);
    EXPECT_TRUE(one.leaf_refs == two.leaf_refs);
    EXPECT_TRUE(one.nodes == four.nodes);
    EXPECT_TRUE(one.leaf_refs == four.leaf_refs);
}

// The figures compute_stats reports, from a plain recursive walk (the oracle); sah_cost sums the
// same terms, in another grouping.
struct StatsOracle {
    uint64_t nodes = 0, leaves = 0, empty_leaves = 0, nonempty = 0, refs_in_nonempty = 0;
    uint64_t depth_sum = 0;
    uint32_t max_depth = 0;
    double cost = 0;

    static double half_area(const Aabb& b) {
        const double x = double{b.hi.x} - b.lo.x, y = double{b.hi.y} - b.lo.y,
                     z = double{b.hi.z} - b.lo.z;
        return x * y + y * z + z * x;
    }

    void visit(const KdTree& tree, uint32_t index, uint32_t depth, Aabb cell, double root_area) {
        const KdNode node = tree.nodes[index];
        const double p = half_area(cell) / root_area;
        ++nodes;
        if (node.is_leaf()) {
            ++leaves;
            depth_sum += depth;
            max_depth = std::max(max_depth, depth);
            if (node.prim_count() == 0) {
                ++empty_leaves;
            } else {
                ++nonempty;
                refs_in_nonempty += node.prim_count();
            }
            cost += p * tree.options.intersection_cost * node.prim_count();
            return;
        }
        cost += p * tree.options.traversal_cost;
        Aabb left = cell, right = cell;
        left.hi[node.axis()] = node.split();
        right.lo[node.axis()] = node.split();
        visit(tree, node.first_child(), depth + 1, left, root_area);
        visit(tree, node.first_child() + 1, depth + 1, right, root_area);
    }
};

TEST(KdBuild, StatsMatchTheOracleAndAreTheSameAtAnyThreadCount) {
    Rng rng(test_seed() + 102);
    const Mesh mesh = random_soup(rng, 80000);
    const KdTree tree = build_kdtree(mesh);
    ASSERT_GT(tree.nodes.size(), size_t{1} << 16) << "big enough for the parallel walk";
    StatsOracle o;
    o.visit(tree, 0, 0, tree.bounds, StatsOracle::half_area(tree.bounds));
    const TreeStats& s = tree.stats;
    EXPECT_EQ(s.nodes, o.nodes);
    EXPECT_EQ(s.leaves, o.leaves);
    EXPECT_EQ(s.empty_leaves, o.empty_leaves);
    EXPECT_EQ(s.max_depth, o.max_depth);
    EXPECT_EQ(s.mean_leaf_depth, static_cast<double>(o.depth_sum) / static_cast<double>(o.leaves));
    EXPECT_EQ(s.mean_tris_per_leaf,
              static_cast<double>(o.refs_in_nonempty) / static_cast<double>(o.nonempty));
    EXPECT_NEAR(s.sah_cost, o.cost, 1e-12 * o.cost) << "the same terms, grouped otherwise";
    for (const int threads : {1, 2, 4}) {
        tbb::task_arena arena(threads);
        const TreeStats t = arena.execute([&] { return compute_stats(tree); });
        EXPECT_EQ(t.nodes, s.nodes) << threads << " threads";
        EXPECT_EQ(t.leaves, s.leaves) << threads << " threads";
        EXPECT_EQ(t.empty_leaves, s.empty_leaves) << threads << " threads";
        EXPECT_EQ(t.max_depth, s.max_depth) << threads << " threads";
        EXPECT_EQ(t.mean_leaf_depth, s.mean_leaf_depth) << threads << " threads";
        EXPECT_EQ(t.mean_tris_per_leaf, s.mean_tris_per_leaf) << threads << " threads";
        EXPECT_EQ(t.sah_cost, s.sah_cost) << threads << " threads: every bit";
        EXPECT_EQ(t.bytes, s.bytes) << threads << " threads";
    }
}

TEST(KdBuild, SahTreeHasTheExpectedShape) {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
    ASSERT_TRUE(mesh.ok());
    const KdTree sah = build_kdtree(*mesh);
    BuildOptions middle_opts;
    middle_opts.builder = Builder::kMiddle;
    const KdTree middle = build_kdtree(*mesh, middle_opts);
    const TreeStats& s = sah.stats;
    EXPECT_EQ(s.triangles, 75408u);
    EXPECT_EQ(s.nodes, 2 * s.leaves - 1);
    EXPECT_GT(s.max_depth, 20u) << "a SAH tree is deep and stringy";
    EXPECT_GT(s.empty_leaves, s.leaves / 10) << "and cuts off empty space";
    EXPECT_LT(s.mean_tris_per_leaf, 12.0)
        << "leaves hold a few triangles (C_isect 0.3: about 9 on the bunny)";
    EXPECT_LT(s.sah_cost, middle.stats.sah_cost)
        << "SAH must beat the middle-split tree on its own metric";
    EXPECT_EQ(s.bytes, sah.nodes.size() * 8 + sah.wide_nodes.size() * 64 + s.refs * 4 +
                           s.triangles * (sizeof(TriVerts) + 8))
        << "nodes, wide nodes, references, triangles and their two id maps";
    EXPECT_LE(s.bytes_per_triangle, 88.0) << "within Embree's bytes per triangle";
    EXPECT_EQ(sah.nodes.size(), s.nodes + 1) << "the line layout leaves one slot unused";
    EXPECT_GT(s.build_ms, 0.0);
}

TEST(KdDegenerate, EmptyMeshMissesEverything) {
    const Mesh mesh;
    const KdTree tree = build_kdtree(mesh);
    EXPECT_EQ(tree.stats.triangles, 0u);
    EXPECT_EQ(tree.nodes.size(), 1u);
    const Hit h = intersect(tree, make_ray({0, 0, -1}, {0, 0, 1}));
    EXPECT_FALSE(h.is_hit());
    EXPECT_TRUE(std::isinf(h.t));
    EXPECT_FALSE(occluded(tree, make_ray({0, 0, -1}, {0, 0, 1})));
}

TEST(KdDegenerate, OneTriangle) {
    Mesh mesh;
    add_triangle(mesh, {0, 0, 0}, {1, 0, 0}, {0, 1, 0});
    const KdTree tree = build_kdtree(mesh);
    const Hit h = intersect(tree, make_ray({0.25f, 0.5f, 2}, {0, 0, -1}));
    ASSERT_TRUE(h.is_hit());
    EXPECT_EQ(h.prim, 0u);
    EXPECT_EQ(h.t, 2.0f);
    EXPECT_FLOAT_EQ(h.u, 0.25f);
    EXPECT_FLOAT_EQ(h.v, 0.5f);
    // Hit exactly at tmax and tmin counts; just beyond does not.
    EXPECT_TRUE(intersect(tree, make_ray({0.25f, 0.5f, 2}, {0, 0, -1}, 0, 2.0f)).is_hit());
    EXPECT_TRUE(intersect(tree, make_ray({0.25f, 0.5f, 2}, {0, 0, -1}, 2.0f, 2.0f)).is_hit());
    EXPECT_FALSE(
        intersect(tree, make_ray({0.25f, 0.5f, 2}, {0, 0, -1}, 0, std::nextafter(2.0f, 0.0f)))
            .is_hit());
    EXPECT_FALSE(
        intersect(tree, make_ray({0.25f, 0.5f, 2}, {0, 0, -1}, std::nextafter(2.0f, 3.0f), 5))
            .is_hit());
    EXPECT_FALSE(intersect(tree, make_ray({0.75f, 0.75f, 2}, {0, 0, -1})).is_hit());
    EXPECT_TRUE(occluded(tree, make_ray({0.25f, 0.5f, -2}, {0, 0, 1})));  // back side is hit too
}

TEST(KdDegenerate, CoplanarAxisAlignedGrid) {
    Mesh mesh;  // a 64x64 grid of triangle pairs, all in the plane z = 0.5
    const int n = 64;
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) {
            const float x = i / float(n), y = j / float(n), s = 1.0f / n;
            add_triangle(mesh, {x, y, 0.5f}, {x + s, y, 0.5f}, {x + s, y + s, 0.5f});
            add_triangle(mesh, {x, y, 0.5f}, {x + s, y + s, 0.5f}, {x, y + s, 0.5f});
        }
    const KdTree tree = build_kdtree(mesh);
    EXPECT_GT(tree.stats.leaves, 100u) << "planar triangles must still be split up";
    Rng rng(test_seed() + 200);
    std::vector<Ray> rays = oracle_rays(rng, mesh, tree, scaled(50'000));
    for (int i = 0; i < 5000; ++i) {  // rays in the plane itself and straight down onto it
        rays.push_back(make_ray({rng.uniform(), rng.uniform(), 0.5f},
                                {rng.uniform(-1, 1), rng.uniform(-1, 1), 0}));
        rays.push_back(make_ray({rng.uniform(), rng.uniform(), 3.0f}, {0, 0, -1}));
    }
    const auto got = tree_all(tree, rays);
    const std::vector<TriVerts> tris = make_tri_verts(mesh);
    expect_same_hits(got, brute_force_all(tris, rays), rays, tris);
    EXPECT_TRUE(intersect(tree, make_ray({0.3f, 0.3f, 3.0f}, {0, 0, -1})).is_hit());
    EXPECT_FALSE(intersect(tree, make_ray({0.3f, 0.3f, 0.5f}, {1, 0, 0})).is_hit())
        << "edge-on: no area";
}

TEST(KdDegenerate, DuplicateTrianglesTieToTheLowestId) {
    Mesh mesh;
    add_triangle(mesh, {5, 5, 5}, {6, 5, 5}, {5, 6, 5});  // decoy
    for (int i = 0; i < 5; ++i) add_triangle(mesh, {0, 0, 0}, {1, 0, 0}, {0, 1, 0});
    const KdTree tree = build_kdtree(mesh);
    const Hit h = intersect(tree, make_ray({0.2f, 0.2f, 1}, {0, 0, -1}));
    ASSERT_TRUE(h.is_hit());
    EXPECT_EQ(h.prim, 1u);
    EXPECT_EQ(h.t, 1.0f);
}

TEST(KdDegenerate, ZeroAreaTrianglesAreNeverHit) {
    Mesh mesh;
    add_triangle(mesh, {0, 0, 0}, {1, 0, 0}, {2, 0, 0});                    // collinear
    add_triangle(mesh, {0.5f, 0.5f, 0}, {0.5f, 0.5f, 0}, {0.5f, 0.5f, 0});  // a point
    add_triangle(mesh, {0, 0, 1}, {1, 0, 1}, {0, 1, 1});                    // a real one, behind
    const KdTree tree = build_kdtree(mesh);
    EXPECT_EQ(tree.stats.triangles, 3u);
    EXPECT_EQ(tree.stats.refs, 1u) << "degenerate triangles stay out of the tree";
    const Hit h = intersect(tree, make_ray({0.5f, 0, -1}, {0, 0, 1}));  // through the collinear one
    EXPECT_EQ(h.prim, 2u);
    EXPECT_EQ(intersect(tree, make_ray({0.5f, 0.5f, -1}, {0, 0, 1})).prim,
              2u);  // through the point
    EXPECT_EQ(brute_force_intersect(make_tri_verts(mesh), make_ray({0.5f, 0, -1}, {0, 0, 1})).prim,
              2u);
}

TEST(KdDegenerate, InvalidMeshesGiveClearErrors) {
    Mesh nan_mesh;
    add_triangle(nan_mesh, {0, 0, 0}, {1, 0, 0}, {0, 1, 0});
    nan_mesh.positions[4] = NAN;  // vertex 1, y
    try {
        (void)build_kdtree(nan_mesh);
        FAIL() << "NaN accepted";
    } catch (const MeshError& e) {
        EXPECT_STREQ(e.what(), "vertex 1: coordinate y is NaN");
    }
    Mesh inf_mesh = nan_mesh;
    inf_mesh.positions[4] = 0;
    inf_mesh.positions[8] = -INFINITY;
    EXPECT_THROW((void)build_kdtree(inf_mesh), MeshError);
    Mesh bad_index;
    add_triangle(bad_index, {0, 0, 0}, {1, 0, 0}, {0, 1, 0});
    bad_index.indices[2] = 3;
    try {
        validate_mesh(bad_index);
        FAIL() << "index out of range accepted";
    } catch (const MeshError& e) {
        EXPECT_STREQ(e.what(),
                     "triangle 0: corner 2 refers to vertex 3 but the mesh has 3 vertices");
    }
    Mesh ragged;
    ragged.positions = {0, 0};
    EXPECT_THROW(validate_mesh(ragged), MeshError);
}

TEST(KdTrace, InvalidRaysAreMisses) {
    Mesh mesh;
    add_triangle(mesh, {-1, -1, 0}, {1, -1, 0}, {0, 1, 0});
    const KdTree tree = build_kdtree(mesh);
    const Ray good = make_ray({0, 0, 1}, {0, 0, -1});
    ASSERT_TRUE(intersect(tree, good).is_hit());
    for (int field = 0; field < 8; ++field) {
        for (float bad : {NAN, INFINITY, -INFINITY}) {
            Ray r = good;
            std::memcpy(reinterpret_cast<char*>(&r) + sizeof(float) * field, &bad, sizeof bad);
            const bool tmax_inf_ok = field == 7 && bad == INFINITY;
            const bool tmin_ninf_ok = field == 3 && bad == -INFINITY;
            EXPECT_EQ(intersect(tree, r).is_hit(), tmax_inf_ok || tmin_ninf_ok)
                << "field " << field << " = " << bad;
            EXPECT_EQ(occluded(tree, r), tmax_inf_ok || tmin_ninf_ok)
                << "field " << field << " = " << bad;
        }
    }
    EXPECT_FALSE(intersect(tree, make_ray({0, 0, 1}, {0, 0, 0})).is_hit()) << "zero direction";
    EXPECT_FALSE(intersect(tree, make_ray({0, 0, 1}, {0, 0, -1}, 2.0f, 1.0f)).is_hit())
        << "tmin > tmax";
}

}  // namespace
}  // namespace kdrt::test
