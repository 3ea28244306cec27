// Every writer/parser pair returns the bunny unchanged.

#include <gtest/gtest.h>

#include <bit>
#include <cstring>

#include "kdrt/proto/mesh_io.h"
#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

const Mesh& bunny() {
    static const Mesh mesh = [] {
        auto r = load_mesh_file(test::test_data("bunny00.off"));
        if (!r) ADD_FAILURE() << r.error().to_string();
        return r ? std::move(r).value() : Mesh{};
    }();
    return mesh;
}

struct Encoding {
    const char* name;
    MeshFormat format;
    MeshWriteOptions options;
};

class MeshRoundTrip : public ::testing::TestWithParam<Encoding> {};

TEST_P(MeshRoundTrip, BunnyKeepsPositionsAndIndices) {
    const Encoding& enc = GetParam();
    const Mesh& original = bunny();
    ASSERT_EQ(original.triangle_count(), 75408u);
    const auto bytes = write_mesh(original, enc.format, enc.options);
    const auto parsed = parse_mesh(bytes, enc.format);
    ASSERT_TRUE(parsed.ok()) << parsed.error().message;
    test::expect_well_formed(*parsed);
    // Exact float equality: text writers use the shortest round-trip form.
    EXPECT_TRUE(parsed->positions == original.positions);
    EXPECT_TRUE(parsed->indices == original.indices);
}

INSTANTIATE_TEST_SUITE_P(
    IndexedFormats, MeshRoundTrip,
    ::testing::Values(
        Encoding{"obj", MeshFormat::kObj, {}}, Encoding{"off", MeshFormat::kOff, {}},
        Encoding{"ply_ascii", MeshFormat::kPly, {.binary = false}},
        Encoding{"ply_binary_le", MeshFormat::kPly, {.binary = true, .big_endian = false}},
        Encoding{"ply_binary_be", MeshFormat::kPly, {.binary = true, .big_endian = true}},
        Encoding{"raw", MeshFormat::kRaw, {}}),
    [](const ::testing::TestParamInfo<Encoding>& info) { return std::string(info.param.name); });

/// STL has no shared vertices: compare the three corner positions of every triangle.
void expect_same_triangles(const Mesh& stl, const Mesh& original) {
    ASSERT_EQ(stl.triangle_count(), original.triangle_count());
    ASSERT_EQ(stl.vertex_count(), 3 * original.triangle_count());
    for (size_t t = 0; t < original.triangle_count(); ++t) {
        for (int c = 0; c < 3; ++c) {
            ASSERT_EQ(stl.corner(t, c), original.corner(t, c))
                << "triangle " << t << " corner " << c;
        }
    }
}

TEST(MeshRoundTripStl, AsciiBunny) {
    const auto bytes = write_mesh(bunny(), MeshFormat::kStl, {.binary = false});
    ASSERT_GE(bytes.size(), 6u);
    EXPECT_EQ(std::memcmp(bytes.data(), "solid ", 6), 0);
    const auto parsed = parse_mesh(bytes, MeshFormat::kStl);
    ASSERT_TRUE(parsed.ok()) << parsed.error().message;
    expect_same_triangles(*parsed, bunny());
}

TEST(MeshRoundTripStl, BinaryBunny) {
    const auto bytes = write_mesh(bunny(), MeshFormat::kStl, {.binary = true});
    ASSERT_EQ(bytes.size(), 84u + 50u * 75408u);
    EXPECT_NE(std::memcmp(bytes.data(), "solid", 5), 0);
    const auto parsed = parse_mesh(bytes, MeshFormat::kStl);
    ASSERT_TRUE(parsed.ok()) << parsed.error().message;
    expect_same_triangles(*parsed, bunny());
}

TEST(MeshRoundTripStl, BinaryBunnyWithSolidHeader) {
    // Exporters in the wild write "solid <name>" into the binary header; the size decides.
    auto bytes = write_mesh(bunny(), MeshFormat::kStl, {.binary = true});
    std::memcpy(bytes.data(), "solid bunny exported as binary", 30);
    const auto parsed = parse_mesh(bytes, MeshFormat::kStl);
    ASSERT_TRUE(parsed.ok()) << parsed.error().message;
    expect_same_triangles(*parsed, bunny());
}

TEST(MeshRoundTripStl, BinaryNormalsAreUnitRightHanded) {
    const Mesh tri = test::make_mesh({0, 0, 0, 2, 0, 0, 0, 2, 0}, {0, 1, 2});
    const auto bytes = write_mesh(tri, MeshFormat::kStl);
    float normal[3];
    std::memcpy(normal, bytes.data() + 84, 12);
    EXPECT_EQ(normal[0], 0.0f);
    EXPECT_EQ(normal[1], 0.0f);
    EXPECT_EQ(normal[2], 1.0f);
}

TEST(MeshRoundTrip, ExtremeFloatsSurviveText) {
    // Shortest round-trip text must also hold denormals, huge values and negative zero.
    const Mesh m = test::make_mesh({1e-45f, -3.4028235e38f, -0.0f, 0.1f, 1.0f / 3.0f, 16777217.0f,
                                    1e-38f, 7e-39f, 123456.789f},
                                   {0, 1, 2});
    for (MeshFormat f : {MeshFormat::kObj, MeshFormat::kOff, MeshFormat::kPly}) {
        const auto parsed = parse_mesh(write_mesh(m, f, {.binary = false}), f);
        ASSERT_TRUE(parsed.ok()) << mesh_format_name(f) << ": " << parsed.error().message;
        for (size_t i = 0; i < m.positions.size(); ++i) {
            EXPECT_EQ(std::bit_cast<uint32_t>(parsed->positions[i]),
                      std::bit_cast<uint32_t>(m.positions[i]))
                << mesh_format_name(f) << " value " << i;
        }
    }
}

TEST(MeshRoundTrip, EmptyMeshInEveryFormat) {
    const Mesh empty;
    for (MeshFormat f : {MeshFormat::kObj, MeshFormat::kOff, MeshFormat::kPly, MeshFormat::kStl,
                         MeshFormat::kRaw}) {
        for (bool binary : {false, true}) {
            const auto parsed = parse_mesh(write_mesh(empty, f, {.binary = binary}), f);
            ASSERT_TRUE(parsed.ok()) << mesh_format_name(f) << ": " << parsed.error().message;
            EXPECT_EQ(parsed->triangle_count(), 0u);
        }
    }
}

}  // namespace
}  // namespace kdrt::proto
