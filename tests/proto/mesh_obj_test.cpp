// OBJ: accepted syntax, triangulation order, and malformed files with their lines.

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "kdrt/proto/errors.h"
#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

using test::parse_error;
using test::parse_ok;
using ::testing::HasSubstr;

constexpr std::string_view kSquare =
    "v 0 0 0\n"
    "v 1 0 0\n"
    "v 1 1 0\n"
    "v 0 1 0\n";

TEST(ObjParse, TrianglesAndPolygonFanInFileOrder) {
    const Mesh m = parse_ok(std::string(kSquare) +
                                "v 0.5 2 0\n"
                                "f 1 2 3\n"
                                "f 1 2 3 5 4\n",
                            MeshFormat::kObj);
    EXPECT_EQ(m.vertex_count(), 5u);
    // Pentagon (0 1 2 4 3) -> (0 1 2) (0 2 4) (0 4 3).
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2, 0, 1, 2, 0, 2, 4, 0, 4, 3}));
    EXPECT_EQ(m.positions[13], 2.0f);
}

TEST(ObjParse, NegativeIndicesAreRelativeToVerticesSoFar) {
    const Mesh m = parse_ok(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\n"
        "f -3 -2 -1\n"
        "v 5 5 5\n"
        "f -1 -2 -4 2\n",
        MeshFormat::kObj);
    // Second face: -1 -> vertex 3, -2 -> 2, -4 -> 0, 2 -> 1.
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2, 3, 2, 0, 3, 0, 1}));
}

TEST(ObjParse, CornerForms) {
    const Mesh m = parse_ok(std::string(kSquare) +
                                "vt 0 0\nvt 1 0\nvt 1 1\n"
                                "vn 0 0 1\n"
                                "f 1/1/1 2/2/1 3/3/1\n"
                                "f 1//1 3//1 4//1\n"
                                "f 4/1 3/2 2/3\n"
                                "f -4/-3/-1 -3//-1 -2/1\n",
                            MeshFormat::kObj);
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2, 0, 2, 3, 3, 2, 1, 0, 1, 2}));
}

TEST(ObjParse, IgnoresOtherStatementsCommentsAndExtras) {
    const Mesh m = parse_ok(
        "# exported by something\n"
        "mtllib scene.mtl\n"
        "o Thing\n"
        "g group1 group2\n"
        "s off\n"
        "usemtl red\n"
        "v 0 0 0 1.0\n"              // w
        "v 1 0 0 1.0 0.5 0.5 0.5\n"  // w + colour
        "v 0 1 0   # trailing comment\n"
        "vp 0.5\n"
        "l 1 2\n"
        "p 3\n"
        "\n"
        "   \t  \n"
        "f 1 2 3\n",
        MeshFormat::kObj);
    EXPECT_EQ(m.vertex_count(), 3u);
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2}));
}

TEST(ObjParse, CrlfTabsContinuationAndBom) {
    const Mesh m = parse_ok(
        "\xEF\xBB\xBFv\t0 0 0\r\n"
        "v 1 0 0\r\n"
        "v 0 \\\r\n"
        "  1 0\r\n"
        "f 1 \\\n"
        "2 \\\n"
        "3\r\n",
        MeshFormat::kObj);
    EXPECT_EQ(m.positions, (std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0}));
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2}));
}

TEST(ObjParse, LineNumbersCountPhysicalLinesAfterContinuations) {
    const auto e = parse_error(
        "v 0 0 \\\n"
        "0\n"
        "v 1 0 0\n"
        "f 1 2 3\n",  // line 4
        MeshFormat::kObj);
    EXPECT_EQ(e.line, 4u);
    EXPECT_THAT(
        e.message,
        HasSubstr("line 4: face index 3 refers to a vertex not defined yet (2 vertices so far)"));
}

TEST(ObjParse, EmptyFileIsAnEmptyMesh) {
    const Mesh m = parse_ok("", MeshFormat::kObj);
    EXPECT_EQ(m.vertex_count(), 0u);
    EXPECT_EQ(m.triangle_count(), 0u);
}

// ---- malformed files ----

TEST(ObjMalformed, FaceBeforeVertices) {
    const auto e = parse_error("f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 1u);
    EXPECT_THAT(e.message, HasSubstr(errors::kUndefinedVertex));
    EXPECT_THAT(e.message, HasSubstr("(0 vertices so far)"));
}

TEST(ObjMalformed, BadNumber) {
    const auto e = parse_error(std::string(kSquare) + "v 1 2x 3\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 5u);
    EXPECT_EQ(e.message, "line 5: vertex 4 coordinate y '2x' is not a number");
    EXPECT_THAT(e.message, HasSubstr(errors::kNotANumber));
}

TEST(ObjMalformed, NanAndInfCoordinates) {
    auto e = parse_error("v 0 0 0\nv nan 0 0\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 2u);
    EXPECT_EQ(e.message, "line 2: vertex 1 coordinate x 'nan' is not finite");
    e = parse_error("v 0 0 -inf\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 1u);
    EXPECT_THAT(e.message, HasSubstr("coordinate z '-inf' " + std::string(errors::kNonFinite)));
    e = parse_error("v 0 1e39 0\n", MeshFormat::kObj);
    EXPECT_THAT(e.message,
                HasSubstr("'1e39' " + std::string(errors::kNumberOutOfRange) + " in a float"));
}

TEST(ObjMalformed, IndexOutOfRange) {
    auto e = parse_error(std::string(kSquare) + "f 1 2 3\nf 1 2 5\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 6u);
    EXPECT_THAT(e.message,
                HasSubstr("face index 5 refers to a vertex not defined yet (4 vertices so far)"));
    e = parse_error(std::string(kSquare) + "f -5 1 2\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 5u);
    EXPECT_THAT(e.message, HasSubstr("face index -5 is " + std::string(errors::kIndexOutOfRange)));
    e = parse_error(std::string(kSquare) + "f 0 1 2\n", MeshFormat::kObj);
    EXPECT_THAT(e.message, HasSubstr("face index 0 is out of range (OBJ indices start at 1)"));
    e = parse_error(std::string(kSquare) + "f 1 2 99999999999999999999\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 5u);
    EXPECT_THAT(e.message, HasSubstr("face index '99999999999999999999' is out of range"));
}

TEST(ObjMalformed, TooFewCorners) {
    const auto e = parse_error(std::string(kSquare) + "f 1 2\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 5u);
    EXPECT_EQ(e.message, "line 5: face has 2 vertices, a face needs at least 3 vertices");
}

TEST(ObjMalformed, MissingCoordinate) {
    const auto e = parse_error("v 1 2\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 1u);
    EXPECT_THAT(e.message, HasSubstr(errors::kMissingCoordinate));
}

TEST(ObjMalformed, BadCornerForms) {
    for (const char* corner : {"1/", "1/2/", "1//", "1/a/2", "x", "1/2/3/4", "1/ 2"}) {
        const auto e =
            parse_error(std::string(kSquare) + "f 2 3 " + corner + "\n", MeshFormat::kObj);
        EXPECT_EQ(e.line, 5u) << corner;
        EXPECT_THAT(e.message, HasSubstr("is not of the form v, v/vt, v//vn or v/vt/vn")) << corner;
    }
}

TEST(ObjMalformed, UnknownStatementRejectsOtherFormats) {
    auto e = parse_error("v 0 0 0\nvx 1 2 3\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 2u);
    EXPECT_THAT(e.message, HasSubstr(std::string(errors::kUnknownStatement) + " 'vx'"));
    e = parse_error("ply\nformat ascii 1.0\n", MeshFormat::kObj);
    EXPECT_EQ(e.line, 1u);
    e = parse_error(std::string("\x01\x02\x00\x05", 4), MeshFormat::kObj);
    EXPECT_THAT(e.message, HasSubstr("'\\x01\\x02\\x00\\x05'"));
}

TEST(ObjMalformed, Limits) {
    MeshLimits limits;
    limits.max_vertices = 3;
    auto e = parse_error(kSquare, MeshFormat::kObj, limits);
    EXPECT_EQ(e.line, 4u);
    EXPECT_THAT(e.message,
                HasSubstr("vertex count 4 " + std::string(errors::kLimitExceeded) + " 3"));

    limits = {};
    limits.max_triangles = 2;
    e = parse_error(std::string(kSquare) + "f 1 2 3\nf 1 2 3 4\n", MeshFormat::kObj, limits);
    EXPECT_EQ(e.line, 6u);
    EXPECT_THAT(e.message, HasSubstr("triangle count 3 exceeds the limit 2"));

    limits = {};
    limits.max_polygon_vertices = 4;
    EXPECT_EQ(
        parse_ok(std::string(kSquare) + "f 1 2 3 4\n", MeshFormat::kObj, limits).triangle_count(),
        2u);
    e = parse_error(std::string(kSquare) + "f 1 2 3 4 1\n", MeshFormat::kObj, limits);
    EXPECT_EQ(e.line, 5u);
    EXPECT_THAT(e.message, HasSubstr(errors::kTooManyCorners));
}

}  // namespace
}  // namespace kdrt::proto
