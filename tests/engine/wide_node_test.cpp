// Wide nodes (KdTree::wide_nodes, make_wide_nodes in engine/src/node_layout.cpp) and the
// single-ray kernel over them (engine/src/wide_kernel.h): the bit layout, the conversion back to
// the binary tree, and the kernel of every ISA against brute force on adversarial rays.

#include <gtest/gtest.h>

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <limits>
#include <span>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/trace.h"
#include "oracle.h"
#include "scenes.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

static_assert(sizeof(WideNode) == 64 && alignof(WideNode) == 64, "one cache line");
static_assert(offsetof(WideNode, split) == 0 && offsetof(WideNode, axes) == 28 &&
              offsetof(WideNode, slot) == 32);
static_assert(WideNode::kSlotNone == 0 && WideNode::kSlotEmpty == 1 && WideNode::kSlotLeaf == 2 &&
              WideNode::kSlotNode == 3);

TEST(WideNodeLayout, SlotWordsAndAxisBitsAreAsDocumented) {
    const uint32_t s = WideNode::make_slot(WideNode::kSlotLeaf, 12345);
    EXPECT_EQ(s, (12345u << 2) | 2u);
    EXPECT_EQ(WideNode::slot_tag(s), WideNode::kSlotLeaf);
    EXPECT_EQ(WideNode::slot_index(s), 12345u);
    EXPECT_EQ(WideNode::slot_index(WideNode::make_slot(WideNode::kSlotNode, KdNode::kMaxField)),
              KdNode::kMaxField);
    WideNode w{};
    w.axes = 0u | (1u << 2);  // plane 0 on x, plane 1 on y, the rest on z
    for (int j = 2; j < WideNode::kPlanes; ++j) w.axes |= 2u << (2 * j);
    EXPECT_EQ(w.axis(0), 0);
    EXPECT_EQ(w.axis(1), 1);
    for (int j = 2; j < WideNode::kPlanes; ++j) EXPECT_EQ(w.axis(j), 2);
    unsigned char bytes[64];
    w.split[3] = 1.5f;
    w.slot[5] = s;
    std::memcpy(bytes, &w, sizeof bytes);
    uint32_t word;
    std::memcpy(&word, bytes + 28, 4);
    EXPECT_EQ(word, w.axes);
    std::memcpy(&word, bytes + 32 + 5 * 4, 4);
    EXPECT_EQ(word, s);
    float f;
    std::memcpy(&f, bytes + 3 * 4, 4);
    EXPECT_EQ(f, 1.5f);
}

TEST(WideNodeLayout, ShallowLeavesArePaddedAndDeepSubtreesGetTheirOwnNode) {
    // root (x = 1): low child a leaf of 2 triangles; high child (y = 2) with an empty leaf low and
    // (z = 3) high, whose children are a leaf and an inner node (x = 4) over two leaves.
    std::vector<KdNode> nodes(9);
    nodes[0] = KdNode::inner(0, 1.0f, 1);
    nodes[1] = KdNode::leaf(2, 0);
    nodes[2] = KdNode::inner(1, 2.0f, 3);
    nodes[3] = KdNode::leaf(0, 2);
    nodes[4] = KdNode::inner(2, 3.0f, 5);
    nodes[5] = KdNode::leaf(1, 2);
    nodes[6] = KdNode::inner(0, 4.0f, 7);
    nodes[7] = KdNode::leaf(1, 3);
    nodes[8] = KdNode::leaf(1, 4);
    const TreeArray<WideNode> wide = make_wide_nodes(nodes);
    ASSERT_EQ(wide.size(), 2u);
    const WideNode& w = wide[0];
    const float inf = std::numeric_limits<float>::infinity();
    EXPECT_EQ(w.split[0], 1.0f);
    EXPECT_EQ(w.axis(0), 0);
    EXPECT_EQ(w.split[1], inf) << "the leaf's level-1 plane is padding";
    EXPECT_EQ(w.split[3], inf) << "and so is its level-2 plane";
    EXPECT_EQ(w.axis(1), 0);
    EXPECT_EQ(w.split[2], 2.0f);
    EXPECT_EQ(w.axis(2), 1);
    EXPECT_EQ(w.split[5], inf) << "the empty leaf at level 2 is padded once";
    EXPECT_EQ(w.split[6], 3.0f);
    EXPECT_EQ(w.axis(6), 2);
    const uint32_t none = WideNode::kSlotNone;
    // A leaf's slot names its first reference, an empty leaf's its node.
    const uint32_t expected[8] = {WideNode::make_slot(WideNode::kSlotLeaf, 0),
                                  none,
                                  none,
                                  none,
                                  WideNode::make_slot(WideNode::kSlotEmpty, 3),
                                  none,
                                  WideNode::make_slot(WideNode::kSlotLeaf, 2),
                                  WideNode::make_slot(WideNode::kSlotNode, 1)};
    for (int s = 0; s < 8; ++s) EXPECT_EQ(w.slot[s], expected[s]) << "slot " << s;
    const WideNode& c = wide[1];
    EXPECT_EQ(c.split[0], 4.0f);
    EXPECT_EQ(c.slot[0], WideNode::make_slot(WideNode::kSlotLeaf, 3));
    EXPECT_EQ(c.slot[4], WideNode::make_slot(WideNode::kSlotLeaf, 4));
    EXPECT_EQ(c.axes >> 14, 0u) << "unused axis bits stay 0";
    for (int j = 0; j < WideNode::kPlanes; ++j)
        EXPECT_NE((c.axes >> (2 * j)) & 3u, 3u) << "plane " << j << ": no axis code 3";

    EXPECT_TRUE(make_wide_nodes(std::vector<KdNode>{KdNode::leaf(3, 0)}).empty())
        << "a tree of one leaf has no wide node";
    // A leaf's first reference must fit a slot's 30 bits.
    std::vector<KdNode> far_refs(3);
    far_refs[0] = KdNode::inner(0, 1.0f, 1);
    far_refs[1] = KdNode::leaf(1, KdNode::kMaxField);
    far_refs[2] = KdNode::leaf(1, KdNode::kMaxField + 1);
    EXPECT_THROW((void)make_wide_nodes(far_refs), std::length_error);
    far_refs[2] = KdNode::leaf(0, KdNode::kMaxField + 1);  // empty: its slot names its node
    EXPECT_NO_THROW((void)make_wide_nodes(far_refs));
}

/// The binary tree a tree's wide nodes stand for, depth first, low side first: (axis, split
/// bits) for an inner node, (word0, word1) for a leaf. Padding planes are skipped.
void expand(const KdTree& tree, uint32_t wide_index,
            std::vector<std::pair<uint32_t, uint32_t>>& out) {
    const WideNode& w = tree.wide_nodes[wide_index];
    const auto plane = [&](int j) {
        uint32_t bits;
        std::memcpy(&bits, &w.split[j], 4);
        out.emplace_back(static_cast<uint32_t>(w.axis(j)), bits);
    };
    const auto slot = [&](uint32_t s) {
        const uint32_t word = w.slot[s];
        if (WideNode::slot_tag(word) == WideNode::kSlotNode) {
            expand(tree, WideNode::slot_index(word), out);
        } else {
            ASSERT_NE(WideNode::slot_tag(word), WideNode::kSlotNone);
            if (WideNode::slot_tag(word) == WideNode::kSlotEmpty) {
                const KdNode leaf = tree.nodes[WideNode::slot_index(word)];
                ASSERT_TRUE(leaf.is_leaf());
                EXPECT_EQ(leaf.prim_count(), 0u);
                out.emplace_back(leaf.word0(), leaf.word1());
                return;
            }
            // A leaf's slot names its first reference; its run ends at the marked one.
            const uint32_t first = WideNode::slot_index(word);
            uint32_t count = 1;
            while (!(tree.leaf_refs[first + count - 1] & KdTree::kLastRef)) ++count;
            const KdNode leaf = KdNode::leaf(count, first);
            out.emplace_back(leaf.word0(), leaf.word1());
        }
    };
    plane(0);
    for (uint32_t b0 = 0; b0 < 2; ++b0) {
        if (std::isinf(w.split[1 + b0])) {
            for (uint32_t s = 4 * b0 + 1; s < 4 * b0 + 4; ++s)
                EXPECT_EQ(w.slot[s], WideNode::kSlotNone);
            slot(4 * b0);
            continue;
        }
        plane(static_cast<int>(1 + b0));
        for (uint32_t b1 = 0; b1 < 2; ++b1) {
            const int p2 = static_cast<int>(3 + 2 * b0 + b1);
            if (std::isinf(w.split[p2])) {
                EXPECT_EQ(w.slot[4 * b0 + 2 * b1 + 1], WideNode::kSlotNone);
                slot(4 * b0 + 2 * b1);
                continue;
            }
            plane(p2);
            slot(4 * b0 + 2 * b1);
            slot(4 * b0 + 2 * b1 + 1);
        }
    }
}

void expect_wide_nodes_are_the_tree(const KdTree& tree, const std::string& what) {
    if (tree.nodes[0].is_leaf()) {
        EXPECT_TRUE(tree.wide_nodes.empty()) << what;
        return;
    }
    ASSERT_FALSE(tree.wide_nodes.empty()) << what;
    std::vector<std::pair<uint32_t, uint32_t>> wide;
    expand(tree, 0, wide);
    EXPECT_TRUE(wide == tree_shape(tree.nodes)) << what;
    // Children after their parents (the conversion numbers them depth first).
    for (size_t i = 0; i < tree.wide_nodes.size(); ++i) {
        for (uint32_t word : tree.wide_nodes[i].slot) {
            if (WideNode::slot_tag(word) == WideNode::kSlotNode) {
                EXPECT_GT(WideNode::slot_index(word), i) << what;
            }
        }
    }
}

TEST(WideNodeLayout, BunnyAndSoupTreesExpandBackToTheBinaryTree) {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
    ASSERT_TRUE(mesh.ok());
    const KdTree bunny = build_kdtree(*mesh);
    expect_wide_nodes_are_the_tree(bunny, "bunny");
    // A wide node stands for several binary inner nodes: about a third as many dependent loads.
    const size_t inner = bunny.stats.nodes - bunny.stats.leaves;
    EXPECT_LT(bunny.wide_nodes.size() * 3, inner) << inner << " inner nodes";
    BuildOptions middle;
    middle.builder = Builder::kMiddle;
    expect_wide_nodes_are_the_tree(build_kdtree(*mesh, middle), "bunny, middle split");
    Rng rng(test_seed());
    for (size_t n : {3, 40, 1000}) {
        const Mesh soup = random_soup(rng, n);
        expect_wide_nodes_are_the_tree(build_kdtree(soup), "soup of " + std::to_string(n));
    }
}

// make_wide_nodes counts the treelets first and allocates its array once at that size: grown
// element by element, every doubling was a fresh (2 MiB-aligned, huge-page) allocation to fault in
// and copy, and the array kept up to half its capacity as slack.
TEST(WideNodeLayout, WideNodesAreAllocatedOnceAtTheirFinalSize) {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
    ASSERT_TRUE(mesh.ok());
    const KdTree bunny = build_kdtree(*mesh);
    const size_t n = bunny.wide_nodes.size();
    // Growth by doubling ends at a power of two: the bunny's count is none, so slack would show.
    ASSERT_NE(n & (n - 1), 0u) << n << " wide nodes";
    EXPECT_EQ(bunny.wide_nodes.capacity(), n);
    const TreeArray<WideNode> again = make_wide_nodes(bunny.nodes);
    ASSERT_EQ(again.size(), n);
    EXPECT_EQ(again.capacity(), n);
    EXPECT_EQ(std::memcmp(again.data(), bunny.wide_nodes.data(), n * sizeof(WideNode)), 0)
        << "the same nodes, in the same order";
    Rng rng(test_seed() ^ 0x31de);
    for (size_t tris : {1, 5, 300, 3000}) {
        const KdTree soup = build_kdtree(random_soup(rng, tris));
        EXPECT_EQ(soup.wide_nodes.capacity(), soup.wide_nodes.size()) << tris << " triangles";
        expect_wide_nodes_are_the_tree(soup, "soup of " + std::to_string(tris));
    }
}

std::vector<Isa> isas_here() {
    std::vector<Isa> out;
    for (Isa isa : {Isa::kScalar, Isa::kSse4, Isa::kAvx2, Isa::kAvx512})
        if (isa_supported(isa)) out.push_back(isa);
    return out;
}

/// Every ISA's single-ray kernel on `rays`: closest hits against the brute-force `want` (ties as
/// the oracle helpers accept them), occlusion against `want_occ`.
void expect_single_rays_answer(const KdTree& tree, std::span<const TriVerts> tris,
                               std::span<const Ray> rays, std::span<const Hit> want,
                               const std::vector<uint8_t>& want_occ, const std::string& what) {
    for (Isa isa : isas_here()) {
        SCOPED_TRACE(what + " / " + std::string(isa_name(isa)));
        std::vector<Hit> got(rays.size());
        intersect(tree, rays, got, {TraceMode::kSingle, isa});
        expect_same_hits(got, want, rays, tris);
        std::vector<uint8_t> occ(rays.size());
        occluded(tree, rays, occ, {TraceMode::kSingle, isa});
        EXPECT_TRUE(occ == want_occ);
    }
}

/// Single rays of every ISA's wide kernel against brute force: closest hits (ties as the oracle
/// helpers accept them) and occlusion, on oracle_rays' adversarial mix (axis-parallel rays, rays
/// in split planes, through vertices and edge midpoints, from inside, tmin/tmax windows).
void expect_single_rays_match_brute_force(const Mesh& mesh, const std::string& what) {
    const KdTree tree = build_kdtree(mesh);
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    Rng rng(test_seed() ^ 0x5157);
    const std::vector<Ray> rays = oracle_rays(rng, mesh, tree, scaled(6000));
    const std::vector<Hit> want = brute_force_all(tris, rays);
    std::vector<uint8_t> want_occ(rays.size());
    for (size_t i = 0; i < rays.size(); ++i)
        want_occ[i] = brute_force_occluded(tris, rays[i]) ? 1 : 0;
    expect_single_rays_answer(tree, tris, rays, want, want_occ, what);
}

TEST(WideKernel, MatchesBruteForceOnAdversarialRaysEveryIsa) {
    Rng rng(test_seed() ^ 0xA11);
    expect_single_rays_match_brute_force(random_soup(rng, 2000), "soup");
    expect_single_rays_match_brute_force(random_soup(rng, 300, 0.6f), "big triangles");
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
    ASSERT_TRUE(mesh.ok());
    expect_single_rays_match_brute_force(*mesh, "bunny");
}

/// Single-ray batches walk several rays in turn (trace_in_turn): every answer must land at its own
/// ray's index and be that ray's single-ray answer, whatever the batch size, wherever the invalid
/// rays and the rays that miss the tree's box fall, and however long each walk is.
void expect_batches_answer_in_place(const Mesh& mesh, const std::string& what) {
    const KdTree tree = build_kdtree(mesh);
    Rng rng(test_seed() ^ 0x7A12);
    std::vector<Ray> pool = oracle_rays(rng, mesh, tree, 60);
    const float nan = std::numeric_limits<float>::quiet_NaN();
    Ray bad = pool[0];
    bad.ox = nan;  // invalid: answered as a miss before any walk
    pool.push_back(bad);
    bad = pool[1];
    bad.dx = bad.dy = bad.dz = 0.0f;  // invalid: no direction
    pool.push_back(bad);
    const Aabb& box = tree.bounds;
    // Valid, but outside the box and pointing away from it: no walk either.
    Ray away{};
    away.ox = box.hi.x + 1.0f;
    away.oy = box.hi.y + 1.0f;
    away.oz = box.hi.z + 1.0f;
    away.dx = 1.0f;
    away.dy = 0.5f;
    away.dz = 0.25f;
    away.tmax = std::numeric_limits<float>::infinity();
    pool.push_back(away);
    // Every size up to 13, then around one, two and three times the walks in turn (16): a batch
    // longer than the walks has walks that end and take the next ray while others go on.
    std::vector<size_t> sizes;
    for (size_t n = 0; n <= 13; ++n) sizes.push_back(n);
    for (size_t n : {15u, 16u, 17u, 31u, 32u, 33u, 47u, 49u, 70u}) sizes.push_back(n);
    for (Isa isa : isas_here()) {
        for (size_t n : sizes) {
            SCOPED_TRACE(what + " / " + std::string(isa_name(isa)) + " / batch of " +
                         std::to_string(n));
            std::vector<Ray> batch(n);
            for (Ray& r : batch) r = pool[rng.below(static_cast<uint32_t>(pool.size()))];
            std::vector<Hit> got(n);
            TraceStats stats;
            intersect(tree, batch, got, {TraceMode::kSingle, isa}, &stats);
            EXPECT_EQ(stats.single_rays + stats.invalid_rays, n);
            EXPECT_EQ(stats.packet_rays, 0u);
            std::vector<Hit> got_block(n);
            intersect_block(tree, batch, got_block, {TraceMode::kSingle, isa});
            std::vector<uint8_t> occ(n), occ_block(n);
            occluded(tree, batch, occ, {TraceMode::kSingle, isa});
            occluded_block(tree, batch, occ_block, {TraceMode::kSingle, isa});
            for (size_t i = 0; i < n; ++i) {
                const Hit want = intersect(tree, batch[i]);
                EXPECT_EQ(std::memcmp(&got[i], &want, sizeof(Hit)), 0)
                    << "ray " << i << ": got t=" << got[i].t << " prim=" << got[i].prim
                    << ", want t=" << want.t << " prim=" << want.prim;
                EXPECT_EQ(std::memcmp(&got_block[i], &want, sizeof(Hit)), 0) << "block, ray " << i;
                const uint8_t want_occ = occluded(tree, batch[i]) ? 1 : 0;
                EXPECT_EQ(occ[i], want_occ) << "ray " << i;
                EXPECT_EQ(occ_block[i], want_occ) << "block, ray " << i;
            }
        }
    }
}

TEST(WideKernel, SingleBatchesWalkedInTurnAnswerEveryRayInPlace) {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
    ASSERT_TRUE(mesh.ok());
    expect_batches_answer_in_place(*mesh, "bunny");
    Mesh one;  // a tree of one leaf: no wide node at all
    add_triangle(one, {0, 0, 0}, {1, 0, 0}, {0, 1, 0});
    const KdTree one_tree = build_kdtree(one);
    ASSERT_TRUE(one_tree.wide_nodes.empty());
    expect_batches_answer_in_place(one, "one triangle");
    Rng rng(test_seed() ^ 0x51);
    expect_batches_answer_in_place(random_soup(rng, 500), "soup");
}

/// The single-ray walk's set-up (the ray's reciprocal, shear, tolerance and box clip, three axes
/// in one vector) and its leaf runs (read four references at a time, except within four of the
/// array's end) against brute force on every ISA: rays with zero and negative-zero direction
/// components whose origins lie inside, outside and on the box's slabs, rays along each axis in
/// either direction (every kz and winding), and rays at the triangles whose references end the
/// reference array.
TEST(WideKernel, SetUpAndLastLeafRunsMatchBruteForceEveryIsa) {
    Rng rng(test_seed() ^ 0x5E7);
    const Mesh soup = random_soup(rng, 1500);
    const KdTree tree = build_kdtree(soup);
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    ASSERT_GE(tree.leaf_refs.size(), 4u);
    const Aabb& box = tree.bounds;
    std::vector<Ray> rays;
    const auto centroid = [](const TriVerts& t) {
        return Vec3{(t.v0[0] + t.v1[0] + t.v2[0]) / 3.0f, (t.v0[1] + t.v1[1] + t.v2[1]) / 3.0f,
                    (t.v0[2] + t.v1[2] + t.v2[2]) / 3.0f};
    };
    // At the triangles of the last references (tree.tris is in leaf order), from all around.
    for (size_t back = 1; back <= 6 && back <= tree.leaf_refs.size(); ++back) {
        const uint32_t ref = tree.leaf_refs[tree.leaf_refs.size() - back] & ~KdTree::kLastRef;
        const Vec3 c = centroid(tree.tris[ref]);
        for (int i = 0; i < 40; ++i) {
            const Vec3 o = c + rng.on_sphere() * 2.0f;
            rays.push_back(make_ray(o, c - o));
        }
    }
    // Zero components (+0 and -0): the slab holds the origin (inside, on its faces) or not.
    const float offsets[] = {-0.5f, 0.0f, 0.3f, 1.0f, 1.5f};  // of the box's extent
    for (int zeros = 1; zeros < 8; ++zeros) {
        if (zeros == 7) continue;  // no direction at all: invalid
        for (int trial = 0; trial < 60; ++trial) {
            Vec3 o = rng.in_box(box);
            Vec3 d = rng.on_sphere();
            for (int a = 0; a < 3; ++a) {
                if (!(zeros & (1 << a))) continue;
                d[a] = rng.below(2) ? 0.0f : -0.0f;
                const float at = offsets[rng.below(5)];
                o[a] = box.lo[a] + at * (box.hi[a] - box.lo[a]);
            }
            rays.push_back(make_ray(o, d));
            rays.push_back(make_ray(o, d, 0.1f, 0.6f));
        }
    }
    // Along each axis, both ways, and nearly so: each kz, each winding, ties of |d|.
    for (int a = 0; a < 3; ++a) {
        for (float sign : {1.0f, -1.0f}) {
            for (int trial = 0; trial < 30; ++trial) {
                Vec3 d{rng.uniform(-0.7f, 0.7f), rng.uniform(-0.7f, 0.7f),
                       rng.uniform(-0.7f, 0.7f)};
                d[a] = sign;
                if (trial % 3 == 0) d[(a + 1) % 3] = -sign;  // a tie of the largest magnitude
                const Vec3 o = rng.in_box(box) - d * 2.0f;
                rays.push_back(make_ray(o, d));
            }
        }
    }
    const std::vector<Hit> want = brute_force_all(tris, rays);
    std::vector<uint8_t> want_occ(rays.size());
    for (size_t i = 0; i < rays.size(); ++i)
        want_occ[i] = brute_force_occluded(tris, rays[i]) ? 1 : 0;
    std::vector<Hit> first;
    for (Isa isa : isas_here()) {
        SCOPED_TRACE(std::string(isa_name(isa)));
        std::vector<Hit> got(rays.size());
        intersect(tree, rays, got, {TraceMode::kSingle, isa});
        expect_same_hits(got, want, rays, tris);
        // Every ISA's walk the same, bit for bit.
        if (first.empty()) first = got;
        EXPECT_EQ(std::memcmp(first.data(), got.data(), got.size() * sizeof(Hit)), 0);
        std::vector<uint8_t> occ(rays.size());
        occluded(tree, rays, occ, {TraceMode::kSingle, isa});
        EXPECT_TRUE(occ == want_occ);
    }
}

/// The four-triangle leaf test (wide::intersect4) picks each triangle's nine floats in the ray's
/// frame: kz the direction's largest axis, kx and ky swapped by its sign, six frames in all, so
/// the triangle's last float (v2's z) is its c_x, c_y or c_z, by frame. Rays at every triangle's
/// centroid, along each frame's axis, both ways, closest hit and occlusion, against brute force:
/// a frame whose pick dropped or moved a coordinate loses hits (or finds wrong ones). (A per-ray
/// pick by permutes, measured and not kept in tests/bench/README.md, failed this test on the
/// frames with kx or ky = z when its blend for v2's z was broken.)
TEST(WideKernel, LeafBlocksInEveryRayFrameMatchBruteForce) {
    Rng rng(test_seed() ^ 0xF4A3);
    const Mesh soup = random_soup(rng, 400, 0.3f);
    const KdTree tree = build_kdtree(soup);
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    for (int axis = 0; axis < 3; ++axis) {
        for (float sign : {1.0f, -1.0f}) {
            std::vector<Ray> rays;
            for (const TriVerts& t : tris) {
                const Vec3 c{(t.v0[0] + t.v1[0] + t.v2[0]) / 3.0f,
                             (t.v0[1] + t.v1[1] + t.v2[1]) / 3.0f,
                             (t.v0[2] + t.v1[2] + t.v2[2]) / 3.0f};
                Vec3 d{rng.uniform(-0.6f, 0.6f), rng.uniform(-0.6f, 0.6f),
                       rng.uniform(-0.6f, 0.6f)};
                d[axis] = sign;
                rays.push_back(make_ray(c - d * 3.0f, d));
                rays.push_back(make_ray(c - d * 3.0f, d, 0.0f, 2.5f));  // stops short: occlusion
            }
            const std::vector<Hit> want = brute_force_all(tris, rays);
            std::vector<uint8_t> want_occ(rays.size());
            size_t hits = 0, blocked = 0, missed = 0;
            for (size_t i = 0; i < rays.size(); ++i) {
                want_occ[i] = brute_force_occluded(tris, rays[i]) ? 1 : 0;
                hits += want[i].prim != kNoHit ? 1 : 0;
                blocked += want_occ[i];
                missed += want_occ[i] ? 0 : 1;
            }
            // Nearly every ray at a centroid hits; the short ones are occluded only sometimes.
            ASSERT_GT(hits, rays.size() * 2 / 5);
            ASSERT_GT(blocked, 0u);
            ASSERT_GT(missed, 0u);
            expect_single_rays_answer(tree, tris, rays, want, want_occ,
                                      "axis " + std::to_string(axis) + (sign > 0 ? " +" : " -"));
        }
    }
}

/// On AVX2 and AVX-512 the single-ray walk tests a leaf eight references at a time
/// (wide::intersect8: each lane's row read by its index, an 8x8 transpose, the ray's axes picked
/// from the columns by blends, the spare lanes repeating the run's first triangle). Big
/// triangles through one small region make leaves that no plane can split, with 9 to 24
/// references: full blocks, short last blocks, and every lane position. Rays at points spread
/// over each triangle, in all six ray frames, closest hit and occlusion, against brute force.
TEST(WideKernel, LeafBlocksOfEightMatchBruteForceInEveryLane) {
    Rng rng(test_seed() ^ 0x8B10);
    for (int count : {9, 13, 16, 24}) {
        Mesh m;
        for (int i = 0; i < count; ++i) {
            const Vec3 c{rng.uniform(-0.02f, 0.02f), rng.uniform(-0.02f, 0.02f),
                         rng.uniform(-0.02f, 0.02f)};
            add_triangle(m, c + rng.on_sphere(), c + rng.on_sphere(), c + rng.on_sphere());
        }
        const KdTree tree = build_kdtree(m);
        uint32_t biggest_leaf = 0;
        for (const KdNode& n : tree.nodes)
            if (n.is_leaf() && n.prim_count() > biggest_leaf) biggest_leaf = n.prim_count();
        ASSERT_GT(biggest_leaf, 8u) << count << " triangles";
        const std::vector<TriVerts> tris = triangles_by_id(tree);
        for (int axis = 0; axis < 3; ++axis) {
            for (float sign : {1.0f, -1.0f}) {
                std::vector<Ray> rays;
                for (const TriVerts& t : tris) {
                    for (int k = 0; k < 8; ++k) {
                        float a = rng.uniform(0.0f, 1.0f), b = rng.uniform(0.0f, 1.0f);
                        if (a + b > 1.0f) {
                            a = 1.0f - a;
                            b = 1.0f - b;
                        }
                        Vec3 p;
                        for (int j = 0; j < 3; ++j)
                            p[j] = t.v0[j] + a * (t.v1[j] - t.v0[j]) + b * (t.v2[j] - t.v0[j]);
                        Vec3 d{rng.uniform(-0.6f, 0.6f), rng.uniform(-0.6f, 0.6f),
                               rng.uniform(-0.6f, 0.6f)};
                        d[axis] = sign;
                        rays.push_back(make_ray(p - d * 3.0f, d));
                        rays.push_back(make_ray(p - d * 3.0f, d, 0.0f, 2.9f));
                    }
                }
                const std::vector<Hit> want = brute_force_all(tris, rays);
                std::vector<uint8_t> want_occ(rays.size());
                size_t hits = 0, blocked = 0;
                for (size_t i = 0; i < rays.size(); ++i) {
                    want_occ[i] = brute_force_occluded(tris, rays[i]) ? 1 : 0;
                    hits += want[i].prim != kNoHit ? 1 : 0;
                    blocked += want_occ[i];
                }
                // Every ray aims at a triangle; the short ones stop before most of them.
                ASSERT_GT(hits, rays.size() * 2 / 5);
                ASSERT_GT(blocked, 0u);
                ASSERT_LT(blocked, rays.size());
                expect_single_rays_answer(tree, tris, rays, want, want_occ,
                                          std::to_string(count) + " triangles, axis " +
                                              std::to_string(axis) + (sign > 0 ? " +" : " -"));
            }
        }
    }
}

TEST(WideKernel, AxisAlignedGridRaysAlongAndAcrossEverySplitPlane) {
    // A grid of unit squares in z = 0, 1, 2: many split planes coincide with triangle edges and
    // with the rays below, which run along those planes, through grid vertices, and from inside.
    Mesh m;
    for (int z = 0; z < 3; ++z)
        for (int y = 0; y < 6; ++y)
            for (int x = 0; x < 6; ++x) {
                const Vec3 a{float(x), float(y), float(z)}, b{float(x + 1), float(y), float(z)},
                    c{float(x + 1), float(y + 1), float(z)}, d{float(x), float(y + 1), float(z)};
                add_triangle(m, a, b, c);
                add_triangle(m, a, c, d);
            }
    const KdTree tree = build_kdtree(m);
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    std::vector<Ray> rays;
    for (int y = 0; y <= 12; ++y)
        for (int x = 0; x <= 12; ++x) {
            const float fx = 0.5f * float(x), fy = 0.5f * float(y);
            rays.push_back(make_ray({fx, fy, -1.0f}, {0, 0, 1}));
            rays.push_back(make_ray({fx, fy, 3.5f}, {0, 0, -1}));
            rays.push_back(make_ray({fx, fy, 1.5f}, {0, 0, 1}, 0.0f, 1.0f));
            rays.push_back(make_ray({fx, fy, 0.0f}, {1, 0, 0}));     // in a triangle plane
            rays.push_back(make_ray({-1.0f, fy, 1.0f}, {1, 0, 0}));  // along a split plane
            rays.push_back(make_ray({fx, fy, -1.0f}, {0.25f, 0.5f, 1}));
            rays.push_back(make_ray({fx, fy, 1.0f}, {-0.0f, -0.0f, -1}, 0.5f, 0.5f));
        }
    const std::vector<Hit> want = brute_force_all(tris, rays);
    for (Isa isa : isas_here()) {
        SCOPED_TRACE(std::string(isa_name(isa)));
        std::vector<Hit> got(rays.size());
        intersect(tree, rays, got, {TraceMode::kSingle, isa});
        expect_same_hits(got, want, rays, tris);
    }
}

}  // namespace
}  // namespace kdrt::test
