// OFF: accepted syntax and malformed files with their lines.

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "kdrt/proto/errors.h"
#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

using test::parse_error;
using test::parse_ok;
using ::testing::HasSubstr;

TEST(OffParse, PolygonsFanTriangulated) {
    const Mesh m = parse_ok(
        "OFF\n"
        "5 2 0\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n0.5 2 0\n"
        "3 0 1 2\n"
        "5 0 1 2 4 3\n",
        MeshFormat::kOff);
    EXPECT_EQ(m.vertex_count(), 5u);
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2, 0, 1, 2, 0, 2, 4, 0, 4, 3}));
}

TEST(OffParse, CommentsBlanksCrlfAndCountsOnHeaderLine) {
    const Mesh m = parse_ok(
        "# a comment before the header\r\n"
        "OFF 3 1 3   # counts on the header line\r\n"
        "\r\n"
        "0 0 0\r\n"
        "# between vertices\r\n"
        "1 0 0\r\n"
        "  0\t1   0  \r\n"
        "3 0 1 2\r\n"
        "\r\n",
        MeshFormat::kOff);
    EXPECT_EQ(m.positions, (std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0}));
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2}));
}

TEST(OffParse, ColourVariantsAndFaceColours) {
    const Mesh m = parse_ok(
        "COFF\n3 1\n"
        "0 0 0 255 0 0 255\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n"
        "3 0 1 2 0.5 0.5 0.5 1\n",
        MeshFormat::kOff);
    EXPECT_EQ(m.positions, (std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0}));
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2}));
    EXPECT_EQ(parse_ok("NOFF\n1 0 0\n1 2 3 0 0 1\n", MeshFormat::kOff).vertex_count(), 1u);
    EXPECT_EQ(parse_ok("STCNOFF\n0 0 0\n", MeshFormat::kOff).vertex_count(), 0u);
}

// ---- malformed files ----

TEST(OffMalformed, BadHeader) {
    auto e = parse_error("OFX\n3 1 0\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 1u);
    EXPECT_EQ(e.message, "line 1: bad header: expected 'OFF', found 'OFX'");
    e = parse_error("\n# only a comment\n4OFF\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 3u);
    EXPECT_THAT(e.message, HasSubstr("only the [ST][C][N]OFF variants"));
    e = parse_error("OFF BINARY\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 1u);
    EXPECT_THAT(e.message, HasSubstr(errors::kBadHeader));
    e = parse_error("", MeshFormat::kOff);
    EXPECT_EQ(e.line, 1u);
    EXPECT_THAT(e.message, HasSubstr(errors::kUnexpectedEnd));
}

TEST(OffMalformed, BadCounts) {
    for (const char* counts : {"3", "3 x 0", "-3 1 0", "3 1 0 7", "3.0 1 0"}) {
        const auto e = parse_error(std::string("OFF\n") + counts + "\n", MeshFormat::kOff);
        EXPECT_EQ(e.line, 2u) << counts;
        EXPECT_THAT(e.message, HasSubstr("vertex_count face_count [edge_count]")) << counts;
    }
}

TEST(OffMalformed, TruncatedVertices) {
    const auto e = parse_error("OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 6u);
    EXPECT_EQ(e.message, "line 6: unexpected end of file: expected 4 vertices, found 3");
}

TEST(OffMalformed, TruncatedFaces) {
    const auto e = parse_error("OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2", MeshFormat::kOff);
    EXPECT_EQ(e.line, 6u);
    EXPECT_THAT(e.message, HasSubstr("expected 2 faces, found 1"));
}

TEST(OffMalformed, FaceIndexOutOfRange) {
    const auto e = parse_error("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 40000\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 6u);
    EXPECT_EQ(e.message, "line 6: face index 40000 out of range (mesh has 3 vertices)");
    EXPECT_EQ(parse_error("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 -1 2\n", MeshFormat::kOff).line,
              6u);
}

TEST(OffMalformed, NanCoordinateAndBadNumber) {
    auto e = parse_error("OFF\n3 1 0\n0 0 0\n1 NaN 0\n0 1 0\n3 0 1 2\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 4u);
    EXPECT_EQ(e.message, "line 4: vertex 1 coordinate y 'NaN' is not finite");
    e = parse_error("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0,5\n3 0 1 2\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 5u);
    EXPECT_THAT(e.message, HasSubstr("'0,5' " + std::string(errors::kNotANumber)));
    e = parse_error("OFF\n3 1 0\n0 0 0\n1 0\n0 1 0\n3 0 1 2\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 4u);
    EXPECT_THAT(e.message, HasSubstr(errors::kMissingCoordinate));
}

TEST(OffMalformed, WrongCountsShowAsTrailingDataOrBadFace) {
    // Header says 2 vertices, the file has 3: the third vertex is read as a face.
    auto e = parse_error("OFF\n2 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 5u);
    EXPECT_THAT(e.message, HasSubstr("face has 0 vertices"));  // "0 1 0" read as a face
    // Header says 1 face, the file has 2.
    e = parse_error("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 2 1 0\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 7u);
    EXPECT_THAT(e.message, HasSubstr(errors::kTrailingData));
    EXPECT_THAT(e.message, HasSubstr("header declares 3 vertices and 1 faces"));
}

TEST(OffMalformed, FaceCornerProblems) {
    const std::string head = "OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\n1 1 0\n";
    auto e = parse_error(head + "4 0 1 2\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 7u);
    EXPECT_THAT(e.message, HasSubstr("face declares 4 vertices but lists 3"));
    e = parse_error(head + "2 0 1\n", MeshFormat::kOff);
    EXPECT_THAT(e.message, HasSubstr(errors::kTooFewCorners));
    e = parse_error(head + "3 0 1 x\n", MeshFormat::kOff);
    EXPECT_THAT(e.message, HasSubstr("face index 'x' " + std::string(errors::kNotAnInteger)));
    e = parse_error(head + "three 0 1 2\n", MeshFormat::kOff);
    EXPECT_THAT(e.message,
                HasSubstr("face vertex count 'three' " + std::string(errors::kNotAnInteger)));
}

TEST(OffMalformed, LimitsCheckedBeforeAllocating) {
    // A header claiming 2^40 vertices in a tiny file: refused on the count.
    auto e = parse_error("OFF\n1099511627776 1 0\n0 0 0\n", MeshFormat::kOff);
    EXPECT_EQ(e.line, 2u);
    EXPECT_THAT(e.message,
                HasSubstr("vertex count 1099511627776 " + std::string(errors::kLimitExceeded)));
    // Within the limit but far more than the file holds: a clean end-of-file error.
    e = parse_error("OFF\n200000000 900000000 0\n0 0 0\n", MeshFormat::kOff);
    EXPECT_THAT(e.message, HasSubstr("expected 200000000 vertices, found 1"));
    MeshLimits limits;
    limits.max_polygon_vertices = 3;
    e = parse_error("OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\n1 1 0\n4 0 1 2 3\n", MeshFormat::kOff,
                    limits);
    EXPECT_EQ(e.line, 7u);
    EXPECT_THAT(e.message, HasSubstr(errors::kTooManyCorners));
    limits = {};
    limits.max_triangles = 1;
    e = parse_error("OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\n1 1 0\n4 0 1 2 3\n", MeshFormat::kOff,
                    limits);
    EXPECT_THAT(e.message, HasSubstr("triangle count 2 exceeds the limit 1"));
}

}  // namespace
}  // namespace kdrt::proto
