// STL: ascii/binary detection, accepted syntax, malformed files with their lines or offsets.

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>

#include "kdrt/proto/errors.h"
#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

using test::append_le32;
using test::append_le_f32;
using test::parse_error;
using test::parse_ok;
using ::testing::HasSubstr;

constexpr std::string_view kFacet =
    "  facet normal 0 0 1\n"
    "    outer loop\n"
    "      vertex 0 0 0\n"
    "      vertex 1 0 0\n"
    "      vertex 0 1 0\n"
    "    endloop\n"
    "  endfacet\n";

/// Binary STL with `count` in the header and the given triangles (9 floats each).
std::vector<std::byte> binary_stl(uint32_t count, const std::vector<float>& corners,
                                  std::string_view header = "") {
    std::vector<std::byte> out(80);
    std::memcpy(out.data(), header.data(), std::min<size_t>(header.size(), 80));
    append_le32(out, count);
    for (size_t t = 0; t < corners.size() / 9; ++t) {
        for (int k = 0; k < 3; ++k) append_le_f32(out, 0.0f);  // normal
        for (int k = 0; k < 9; ++k) append_le_f32(out, corners[9 * t + static_cast<size_t>(k)]);
        out.push_back(std::byte{0});
        out.push_back(std::byte{0});
    }
    return out;
}

const std::vector<float> kTwoTriangles = {0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 1, 2, 1, 1, 1, 2, 1};

TEST(StlParse, AsciiThreeVerticesPerTriangle) {
    const Mesh m =
        parse_ok("solid test\n" + std::string(kFacet) + std::string(kFacet) + "endsolid test\n",
                 MeshFormat::kStl);
    EXPECT_EQ(m.triangle_count(), 2u);
    EXPECT_EQ(m.vertex_count(), 6u);
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2, 3, 4, 5}));
    EXPECT_EQ(m.positions,
              (std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 1, 0}));
}

TEST(StlParse, AsciiUppercaseNanNormalsMultipleSolidsAndNoName) {
    const Mesh m = parse_ok(
        "SOLID\r\n"
        "FACET NORMAL nan nan nan\r\nOUTER LOOP\r\nVERTEX 0 0 0\r\nVERTEX 1e0 0 0\r\nVERTEX 0 +1 "
        "0\r\nENDLOOP\r\nENDFACET\r\n"
        "ENDSOLID\r\n"
        "solid second one\n" +
            std::string(kFacet) + "endsolid second one\n",
        MeshFormat::kStl);
    EXPECT_EQ(m.triangle_count(), 2u);
    EXPECT_EQ(m.positions[3], 1.0f);
    EXPECT_EQ(m.positions[7], 1.0f);
}

TEST(StlParse, BinaryAndEmpty) {
    auto r = parse_mesh(binary_stl(2, kTwoTriangles), MeshFormat::kStl);
    ASSERT_TRUE(r.ok()) << r.error().message;
    EXPECT_EQ(r->positions, kTwoTriangles);
    EXPECT_EQ(r->indices, (std::vector<uint32_t>{0, 1, 2, 3, 4, 5}));
    r = parse_mesh(binary_stl(0, {}), MeshFormat::kStl);
    ASSERT_TRUE(r.ok());
    EXPECT_EQ(r->triangle_count(), 0u);
    EXPECT_EQ(parse_ok("solid empty\nendsolid empty\n", MeshFormat::kStl).triangle_count(), 0u);
}

TEST(StlParse, BinaryWhoseHeaderStartsWithSolid) {
    const auto r =
        parse_mesh(binary_stl(2, kTwoTriangles, "solid trap, but binary"), MeshFormat::kStl);
    ASSERT_TRUE(r.ok()) << r.error().message;
    EXPECT_EQ(r->positions, kTwoTriangles);
}

// ---- malformed ascii ----

TEST(StlMalformedAscii, MissingEndsolid) {
    const auto e = parse_error("solid x\n" + std::string(kFacet), MeshFormat::kStl);
    EXPECT_EQ(e.line, 9u);  // the empty line after the final newline
    EXPECT_EQ(e.message, "line 9: unexpected end of file: expected 'facet' or 'endsolid'");
}

TEST(StlMalformedAscii, BadNumber) {
    const auto e = parse_error(
        "solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 zero\n",
        MeshFormat::kStl);
    EXPECT_EQ(e.line, 6u);
    EXPECT_EQ(e.message, "line 6: vertex 2 coordinate z 'zero' is not a number");
    const auto n = parse_error("solid x\nfacet normal 0 0 one\n", MeshFormat::kStl);
    EXPECT_EQ(n.line, 2u);
    EXPECT_THAT(n.message, HasSubstr("facet normal z 'one' " + std::string(errors::kNotANumber)));
}

TEST(StlMalformedAscii, NanVertex) {
    std::string text = "solid x\n" + std::string(kFacet) + std::string(kFacet) + "endsolid\n";
    text.replace(text.rfind("vertex 1 0 0"), 12, "vertex 1 NaN 0");
    const auto e = parse_error(text, MeshFormat::kStl);
    EXPECT_EQ(e.line, 12u);
    EXPECT_THAT(e.message,
                HasSubstr("vertex 4 coordinate y 'NaN' " + std::string(errors::kNonFinite)));
}

TEST(StlMalformedAscii, WrongKeywords) {
    auto e = parse_error("solid x\nfacet normal 0 0 1\nouter lop\n", MeshFormat::kStl);
    EXPECT_EQ(e.line, 3u);
    EXPECT_EQ(e.message, "line 3: expected 'loop', found 'lop'");
    // A facet with four vertices.
    std::string quad(kFacet);
    quad.replace(quad.find("    endloop"), 0, "      vertex 1 1 0\n");
    e = parse_error("solid x\n" + quad + "endsolid\n", MeshFormat::kStl);
    EXPECT_EQ(e.line, 7u);
    EXPECT_THAT(e.message, HasSubstr("expected 'endloop', found 'vertex'"));
    e = parse_error("solid x\nendsolid x\ngarbage\n", MeshFormat::kStl);
    EXPECT_EQ(e.line, 3u);
    EXPECT_THAT(e.message, HasSubstr("expected 'solid' or the end of the file"));
    e = parse_error("solid x\nfacet normal 0 0\n", MeshFormat::kStl);
    EXPECT_THAT(e.message, HasSubstr("expected a normal component"));
}

TEST(StlMalformedAscii, TriangleLimit) {
    MeshLimits limits;
    limits.max_triangles = 1;
    const auto e =
        parse_error("solid x\n" + std::string(kFacet) + std::string(kFacet) + "endsolid\n",
                    MeshFormat::kStl, limits);
    EXPECT_EQ(e.line, 9u);
    EXPECT_THAT(e.message,
                HasSubstr("triangle count 2 " + std::string(errors::kLimitExceeded) + " 1"));
}

TEST(StlMalformed, BrokenBinaryWithSolidHeaderMentionsBothReadings) {
    auto data = binary_stl(2, kTwoTriangles, "solid but binary");
    data.pop_back();  // size no longer matches the count, so it is tried as ascii
    const auto e = parse_error(data, MeshFormat::kStl);
    EXPECT_EQ(e.line, 1u);
    EXPECT_THAT(e.message, HasSubstr("expected 'facet' or 'endsolid'"));
    EXPECT_THAT(e.message, HasSubstr("(and not binary STL either: header says 2 triangles (184 "
                                     "bytes) but the file has 183 bytes)"));
}

TEST(StlMalformedAscii, PlainTextFailureDoesNotMentionBinary) {
    const auto e = parse_error("solid x\n" + std::string(kFacet) + std::string(kFacet),
                               MeshFormat::kStl);  // > 84 bytes
    EXPECT_THAT(e.message, ::testing::Not(HasSubstr("binary")));
}

// ---- malformed binary ----

TEST(StlMalformedBinary, Truncated) {
    auto data = binary_stl(3, kTwoTriangles);  // header says 3, two present
    data.resize(data.size() + 20);             // part of the third
    const auto e = parse_error(data, MeshFormat::kStl);
    EXPECT_EQ(e.byte_offset, 184u);
    EXPECT_EQ(e.message,
              "byte 184: file ends inside triangle 2: header says 3 triangles (234 bytes) but the "
              "file has 204 bytes");
}

TEST(StlMalformedBinary, TrailingBytes) {
    auto data = binary_stl(1, kTwoTriangles);  // header says 1, two present
    const auto e = parse_error(data, MeshFormat::kStl);
    EXPECT_EQ(e.byte_offset, 134u);
    EXPECT_THAT(e.message, HasSubstr(errors::kTrailingData));
    EXPECT_THAT(e.message, HasSubstr("header says 1 triangles (134 bytes) " +
                                     std::string(errors::kSizeMismatch) + " 184 bytes"));
}

TEST(StlMalformedBinary, NanCoordinateNamesItsOffset) {
    std::vector<float> corners = kTwoTriangles;
    corners[13] = std::numeric_limits<float>::infinity();  // triangle 1, vertex 1, y
    const auto e = parse_error(binary_stl(2, corners), MeshFormat::kStl);
    EXPECT_EQ(e.byte_offset, 84u + 50 + 12 + 16);
    EXPECT_THAT(e.message, HasSubstr("triangle 1 vertex 1 coordinate y (+inf) " +
                                     std::string(errors::kNonFinite)));
}

TEST(StlMalformedBinary, TooShortAndNotAscii) {
    const auto e = parse_error(std::vector<std::byte>(50, std::byte{7}), MeshFormat::kStl);
    EXPECT_EQ(e.byte_offset, 50u);
    EXPECT_THAT(e.message,
                HasSubstr(std::string(errors::kTruncated) + " the 84-byte binary STL header"));
    EXPECT_THAT(e.message, HasSubstr("not ascii STL"));
}

TEST(StlMalformedBinary, HugeCountRefusedOnSize) {
    // Four billion triangles claimed in 84 bytes: a size mismatch, nothing allocated.
    const auto e = parse_error(binary_stl(0xFFFFFFFFu, {}), MeshFormat::kStl);
    EXPECT_EQ(e.byte_offset, 84u);
    EXPECT_THAT(e.message, HasSubstr("header says 4294967295 triangles (214748364834 bytes)"));
    MeshLimits limits;
    limits.max_vertices = 5;  // 2 triangles need 6
    const auto v = parse_error(binary_stl(2, kTwoTriangles), MeshFormat::kStl, limits);
    EXPECT_EQ(v.byte_offset, 80u);
    EXPECT_THAT(v.message,
                HasSubstr("vertex count 6 exceeds the limit 5 (STL has 3 vertices per triangle)"));
}

}  // namespace
}  // namespace kdrt::proto
