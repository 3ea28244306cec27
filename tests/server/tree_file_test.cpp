// The store's tree file container: binds the engine blob to its mesh and names each refusal.

#include "store/tree_file.h"

#include <gtest/gtest.h>

#include "kdrt/proto/mesh_id.h"
#include "kdrt/serialize.h"
#include "store/mesh_store.h"
#include "test_util.h"

namespace kdrt::server {
namespace {

using Reason = TreeFileProblem::Reason;

struct Fixture {
    Mesh mesh;
    KdTree tree;
    std::string id;
    std::vector<std::byte> file;
    explicit Fixture(uint64_t seed) {
        test::Rng rng(seed);
        mesh = test::random_soup(rng, 200);
        tree = build_kdtree(mesh);
        id = proto::mesh_id(mesh);
        file = encode_tree_file(id, tree);
    }
};

Reason refusal(std::string_view id, const std::vector<std::byte>& file) {
    auto decoded = decode_tree_file(id, file);
    EXPECT_FALSE(decoded);
    return decoded ? Reason::kMissing : decoded.error().reason;
}

TEST(TreeFile, RoundTripsItsOwnMesh) {
    const Fixture f(1);
    ASSERT_EQ(f.file.size(), kTreeFileHeaderBytes + serialize_tree(f.tree).size());
    auto back = decode_tree_file(f.id, f.file);
    ASSERT_TRUE(back) << back.error().detail;
    EXPECT_EQ(back->nodes, f.tree.nodes);
    EXPECT_EQ(back->tris.size(), f.tree.tris.size());
}

TEST(TreeFile, RefusesTheTreeOfAnotherMesh) {
    const Fixture a(1), b(2);
    ASSERT_EQ(a.tree.tris.size(), b.tree.tris.size());
    auto decoded = decode_tree_file(a.id, b.file);
    ASSERT_FALSE(decoded);
    EXPECT_EQ(decoded.error().reason, Reason::kOtherMesh);
    EXPECT_NE(decoded.error().detail.find(b.id), std::string::npos);
}

TEST(TreeFile, NamesEachKindOfDamage) {
    const Fixture f(3);
    auto truncated = f.file;
    truncated.resize(truncated.size() - 1);
    EXPECT_EQ(refusal(f.id, truncated), Reason::kTruncated);
    truncated.resize(50);
    EXPECT_EQ(refusal(f.id, truncated), Reason::kTruncated);
    EXPECT_EQ(refusal(f.id, {}), Reason::kTruncated);

    auto header = f.file;
    header[20] ^= std::byte{1};  // inside the id: the header checksum catches it
    EXPECT_EQ(refusal(f.id, header), Reason::kCorrupt);
    auto magic = f.file;
    magic[0] = std::byte{'X'};
    EXPECT_EQ(refusal(f.id, magic), Reason::kCorrupt);
    auto blob = f.file;
    blob[blob.size() / 2] ^= std::byte{0x40};
    EXPECT_EQ(refusal(f.id, blob), Reason::kCorrupt);

    // The bare engine blob of an older server, and an engine blob of another version.
    const std::vector<std::byte> bare(f.file.begin() + kTreeFileHeaderBytes, f.file.end());
    EXPECT_EQ(refusal(f.id, bare), Reason::kFormatVersion);
    auto engine_version = f.file;
    engine_version[kTreeFileHeaderBytes + 8] ^= std::byte{3};
    EXPECT_EQ(refusal(f.id, engine_version), Reason::kFormatVersion);
    EXPECT_EQ(reason_label(Reason::kFormatVersion), "format_version");
    EXPECT_EQ(reason_label(Reason::kOtherMesh), "other_mesh");
}

TEST(TreeFile, MeshFromTreeKeepsTheId) {
    const Fixture f(4);
    const Mesh soup = mesh_from_tree(f.tree);
    EXPECT_EQ(soup.triangle_count(), f.mesh.triangle_count());
    EXPECT_EQ(proto::mesh_id(soup), f.id);
}

}  // namespace
}  // namespace kdrt::server
