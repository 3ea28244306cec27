#include <gtest/gtest.h>

#include <cstring>
#include <vector>

#include "kdrt/serialize.h"
#include "oracle.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

KdTree sample_tree() {
    Rng rng(test_seed() + 400);
    return build_kdtree(random_soup(rng, 2000));
}

TEST(TreeBlob, RoundTripGivesIdenticalTreeAndAnswers) {
    const KdTree tree = sample_tree();
    const std::vector<std::byte> blob = serialize_tree(tree);
    const KdTree loaded = deserialize_tree(blob);
    EXPECT_TRUE(loaded.nodes == tree.nodes);
    EXPECT_TRUE(loaded.leaf_refs == tree.leaf_refs);
    EXPECT_TRUE(loaded.tri_ids == tree.tri_ids);
    EXPECT_TRUE(loaded.tri_slots == tree.tri_slots);
    // The wide nodes are not stored: the load derives the same ones the build made.
    ASSERT_EQ(loaded.wide_nodes.size(), tree.wide_nodes.size());
    EXPECT_FALSE(tree.wide_nodes.empty());
    EXPECT_EQ(std::memcmp(loaded.wide_nodes.data(), tree.wide_nodes.data(),
                          tree.wide_nodes.size() * sizeof(WideNode)),
              0);
    EXPECT_EQ(loaded.stats.bytes, tree.stats.bytes);
    EXPECT_EQ(loaded.bounds, tree.bounds);
    EXPECT_EQ(loaded.options, tree.options);
    EXPECT_EQ(loaded.stats.sah_cost, tree.stats.sah_cost);
    EXPECT_EQ(loaded.stats.build_ms, tree.stats.build_ms);
    EXPECT_EQ(
        std::memcmp(loaded.tris.data(), tree.tris.data(), tree.tris.size() * sizeof(TriVerts)), 0);
    EXPECT_EQ(serialize_tree(loaded), blob) << "serialisation is deterministic";
    Rng rng(test_seed() + 401);
    Mesh mesh;  // only bounds matter for oracle_rays' outer box; reuse the tree's triangles
    for (const TriVerts& t : tree.tris)
        add_triangle(mesh, {t.v0[0], t.v0[1], t.v0[2]}, {t.v1[0], t.v1[1], t.v1[2]},
                     {t.v2[0], t.v2[1], t.v2[2]});
    const auto rays = oracle_rays(rng, mesh, tree, scaled(20'000));
    expect_same_hits(tree_all(loaded, rays), tree_all(tree, rays), rays);
}

void expect_refused(std::span<const std::byte> blob, const std::string& phrase) {
    try {
        (void)deserialize_tree(blob);
        ADD_FAILURE() << "blob accepted; expected an error containing \"" << phrase << "\"";
    } catch (const TreeFormatError& e) {
        EXPECT_NE(std::string(e.what()).find(phrase), std::string::npos) << e.what();
    }
}

TEST(TreeBlob, CorruptedBlobsAreRefused) {
    const std::vector<std::byte> blob = serialize_tree(sample_tree());
    for (size_t at : {size_t{200}, blob.size() / 2, blob.size() - 9}) {
        std::vector<std::byte> bad = blob;
        bad[at] ^= std::byte{0x01};
        expect_refused(bad, "checksum");
    }
    std::vector<std::byte> bad_magic = blob;
    bad_magic[0] = std::byte{'X'};
    expect_refused(bad_magic, "bad magic");
    std::vector<std::byte> version = blob;
    version[8] = std::byte{1};
    expect_refused(version, "version 1 is not supported");
    expect_refused(std::span(blob).first(blob.size() - 1), "checksum");
    expect_refused(std::span(blob).first(10), "truncated");
    expect_refused({}, "truncated");
}

TEST(TreeBlob, StructurallyBrokenBlobWithValidChecksumIsRefused) {
    // A blob whose checksum is right but whose content lies (e.g. written by a buggy tool) must
    // still be refused, since traversal trusts child and ref indices.
    KdTree tree = sample_tree();
    ASSERT_FALSE(tree.nodes[0].is_leaf());
    tree.nodes[0] = KdNode::inner(0, 0.5f, 0);  // child index pointing at itself: a cycle
    expect_refused(serialize_tree(tree), "child index 0 out of range");
    KdTree refs = sample_tree();
    refs.leaf_refs[0] = 999999;
    expect_refused(serialize_tree(refs), "names triangle 999999");
    KdTree ids = sample_tree();
    ASSERT_GT(ids.tri_ids.size(), 2u);
    ids.tri_ids[1] = ids.tri_ids[0];  // two slots claim one mesh triangle
    expect_refused(serialize_tree(ids), "out of range or repeated");
    ids.tri_ids[1] = static_cast<uint32_t>(ids.tri_ids.size());
    expect_refused(serialize_tree(ids), "out of range or repeated");
    // A leaf whose run starts inside another's: a kernel reading the first run would stop at the
    // second's last reference.
    KdTree overlap = sample_tree();
    std::vector<uint32_t> leaves;
    for (uint32_t i = 0; i < overlap.nodes.size(); ++i)
        if (overlap.nodes[i].is_leaf() && overlap.nodes[i].prim_count() > 1) leaves.push_back(i);
    ASSERT_GE(leaves.size(), 2u);
    const KdNode second = overlap.nodes[leaves[1]];
    overlap.nodes[leaves[1]] =
        KdNode::leaf(second.prim_count(), overlap.nodes[leaves[0]].first_ref() + 1);
    expect_refused(serialize_tree(overlap), "overlap those of node");
}

TEST(TreeBlob, LeafRunMarksAreDerivedNotStored) {
    // The blob holds plain reference indices; loading marks each leaf's last reference again,
    // exactly as the build did.
    const KdTree tree = sample_tree();
    size_t marks = 0;
    for (uint32_t r : tree.leaf_refs) marks += (r & KdTree::kLastRef) ? 1 : 0;
    ASSERT_GT(marks, 0u);
    KdTree unmarked = tree;
    for (uint32_t& r : unmarked.leaf_refs) r &= ~KdTree::kLastRef;
    const std::vector<std::byte> blob = serialize_tree(tree);
    EXPECT_EQ(serialize_tree(unmarked), blob);
    EXPECT_TRUE(deserialize_tree(blob).leaf_refs == tree.leaf_refs);
}

TEST(TreeBlob, EmptyTreeRoundTrips) {
    const KdTree tree = build_kdtree(Mesh{});
    const KdTree loaded = deserialize_tree(serialize_tree(tree));
    EXPECT_EQ(loaded.nodes.size(), 1u);
    EXPECT_FALSE(intersect(loaded, make_ray({0, 0, 0}, {1, 0, 0})).is_hit());
}

}  // namespace
}  // namespace kdrt::test
