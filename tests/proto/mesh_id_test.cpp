#include "kdrt/proto/mesh_id.h"

#include <gtest/gtest.h>

#include "kdrt/proto/mesh_io.h"
#include "test_util.h"

namespace kdrt::proto {
namespace {

Mesh one_triangle() {
    Mesh m;
    m.positions = {0, 0, 0, 1, 0, 0, 0, 1, 0};
    m.indices = {0, 1, 2};
    return m;
}

TEST(MeshId, KnownAnswers) {
    // SHA-256 of 9 little-endian f32 (0,0,0, 1,0,0, 0,1,0) and of nothing.
    EXPECT_EQ(mesh_id(one_triangle()),
              "d8b87038ed2ace74ed183166f6b0a541eab77f7184d50e65edc4bca5ccb5445a");
    EXPECT_EQ(mesh_id(Mesh{}), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
    EXPECT_EQ(sha256_hex(canonical_triangles(one_triangle())), mesh_id(one_triangle()));
    EXPECT_EQ(canonical_triangles(one_triangle()).size(), kCanonicalTriangleBytes);
}

TEST(MeshId, IndependentOfVertexSharingOrderAndFormat) {
    test::Rng rng(test::test_seed());
    const Mesh soup = test::random_soup(rng, 5000);  // > one hashing block
    // Same triangles, vertices reversed and an unused vertex added.
    Mesh shuffled;
    const size_t n = soup.vertex_count();
    for (size_t i = n; i-- > 0;) test::add_vertex(shuffled, soup.vertex(i));
    test::add_vertex(shuffled, {9, 9, 9});
    for (uint32_t index : soup.indices)
        shuffled.indices.push_back(static_cast<uint32_t>(n - 1 - index));
    EXPECT_EQ(mesh_id(shuffled), mesh_id(soup));
    // Through every file format (STL has no sharing at all).
    for (const MeshFormat format : {MeshFormat::kObj, MeshFormat::kPly, MeshFormat::kOff,
                                    MeshFormat::kStl, MeshFormat::kRaw}) {
        auto parsed = parse_mesh(write_mesh(soup, format), format);
        ASSERT_TRUE(parsed) << parsed.error().message;
        EXPECT_EQ(mesh_id(*parsed), mesh_id(soup)) << mesh_format_name(format);
    }
}

TEST(MeshId, ChangesWithAnyCoordinateOrTriangleOrder) {
    Mesh m = one_triangle();
    m.positions[4] = -0.0f;  // 0.0 -> -0.0: different bits, different id
    EXPECT_NE(mesh_id(m), mesh_id(one_triangle()));
    Mesh rotated = one_triangle();
    rotated.indices = {1, 2, 0};  // same triangle, other first corner
    EXPECT_NE(mesh_id(rotated), mesh_id(one_triangle()));
}

TEST(MeshId, RefusesOutOfRangeIndices) {
    Mesh m = one_triangle();
    m.indices[2] = 3;
    EXPECT_THROW((void)mesh_id(m), std::invalid_argument);
}

TEST(MeshId, Form) {
    EXPECT_TRUE(is_mesh_id(mesh_id(one_triangle())));
    EXPECT_FALSE(is_mesh_id(""));
    EXPECT_FALSE(is_mesh_id(std::string(63, 'a')));
    EXPECT_FALSE(is_mesh_id(std::string(64, 'A')));
    EXPECT_FALSE(is_mesh_id(std::string(63, 'a') + "g"));
    EXPECT_TRUE(is_mesh_id(std::string(64, 'f')));
}

}  // namespace
}  // namespace kdrt::proto
