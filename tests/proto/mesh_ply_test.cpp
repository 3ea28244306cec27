// PLY: all three encodings, property/element skipping, and malformed files with their lines or
// byte offsets.

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <bit>
#include <cmath>
#include <cstring>

#include "kdrt/proto/errors.h"
#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

using test::parse_error;
using test::parse_ok;
using ::testing::HasSubstr;

/// Binary body builder with explicit byte order.
class Body {
public:
    explicit Body(bool big_endian) : big_endian_(big_endian) {}
    template <class T>
    Body& put(T value) {
        uint64_t bits = 0;
        if constexpr (std::is_same_v<T, float>) {
            bits = std::bit_cast<uint32_t>(value);
        } else if constexpr (std::is_same_v<T, double>) {
            bits = std::bit_cast<uint64_t>(value);
        } else {
            bits = static_cast<uint64_t>(static_cast<std::make_unsigned_t<T>>(value));
        }
        for (size_t i = 0; i < sizeof(T); ++i) {
            const size_t shift = 8 * (big_endian_ ? sizeof(T) - 1 - i : i);
            bytes_.push_back(static_cast<std::byte>((bits >> shift) & 0xFF));
        }
        return *this;
    }
    const std::vector<std::byte>& bytes() const { return bytes_; }

private:
    bool big_endian_;
    std::vector<std::byte> bytes_;
};

std::vector<std::byte> file(std::string_view header, const Body& body) {
    // One allocation and two memcpy: vector::insert here trips a GCC 12 -Warray-bounds false
    // positive.
    std::vector<std::byte> out(header.size() + body.bytes().size());
    std::memcpy(out.data(), header.data(), header.size());
    if (!body.bytes().empty())
        std::memcpy(out.data() + header.size(), body.bytes().data(), body.bytes().size());
    return out;
}

constexpr std::string_view kTriangleLeHeader =
    "ply\n"
    "format binary_little_endian 1.0\n"
    "element vertex 3\n"
    "property float x\n"
    "property float y\n"
    "property float z\n"
    "element face 1\n"
    "property list uchar int vertex_indices\n"
    "end_header\n";

Body triangle_body() {
    Body b(false);
    b.put(0.0f).put(0.0f).put(0.0f).put(1.0f).put(0.0f).put(0.0f).put(0.0f).put(1.0f).put(0.0f);
    b.put(uint8_t{3}).put(int32_t{0}).put(int32_t{1}).put(int32_t{2});
    return b;
}

// ---- accepted files ----

TEST(PlyParse, AsciiSkipsOtherPropertiesAndElements) {
    const Mesh m = parse_ok(
        "ply\n"
        "format ascii 1.0\n"
        "comment made by hand\n"
        "obj_info nothing\n"
        "element vertex 4\n"
        "property float nx\n"
        "property double x\n"
        "property list uchar float weights\n"
        "property int y\n"
        "property float z\n"
        "property uchar red\n"
        "element edge 2\n"
        "property list int int ends\n"
        "property int crease\n"
        "element face 2\n"
        "property uchar flags\n"
        "property list uchar uint vertex_indices\n"
        "property list uchar float texcoord\n"
        "end_header\n"
        "0.1 0 2 0.5 0.5 0 0 255\n"  // nx x [2: 0.5 0.5] y z red
        "0.1 1 0 0 1 1\n"
        "0.1 1 1 3.5 1 0 2\n"
        "0.1 0 0 1 3 0\n"
        "2 0 1 7\n"  // [2: 0 1] crease
        "1 2 9\n"
        "0 3 0 1 2 0\n"
        "5 4 0 1 2 3 6 0 0 1 0 1 1\n",
        MeshFormat::kPly);
    EXPECT_EQ(m.positions, (std::vector<float>{0, 0, 0, 1, 0, 1, 1, 1, 0, 0, 1, 3}));
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2, 0, 1, 2, 0, 2, 3}));
}

TEST(PlyParse, AsciiTokensMayCrossLinesAndHeaderMayUseCrlf) {
    const Mesh m = parse_ok(
        "ply\r\nformat ascii 1.0\r\nelement vertex 3\r\nproperty float x\r\nproperty float y\r\n"
        "property float z\r\nelement face 1\r\nproperty list uchar int "
        "vertex_index\r\nend_header\r\n"
        "0 0 0 1\r\n0 0 0 1 0\r\n3\r\n0 1 2\r\n",
        MeshFormat::kPly);
    EXPECT_EQ(m.positions, (std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0}));
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{0, 1, 2}));
}

TEST(PlyParse, FaceElementBeforeVertexElement) {
    const Mesh m = parse_ok(
        "ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
        "element vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        "3 2 1 0\n0 0 0\n1 0 0\n0 1 0\n",
        MeshFormat::kPly);
    EXPECT_EQ(m.indices, (std::vector<uint32_t>{2, 1, 0}));
    EXPECT_EQ(m.vertex_count(), 3u);
}

TEST(PlyParse, PointCloudWithoutFacesIsAMeshWithoutTriangles) {
    const Mesh m = parse_ok(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n1 2 3\n4 5 6\n",
        MeshFormat::kPly);
    EXPECT_EQ(m.vertex_count(), 2u);
    EXPECT_EQ(m.triangle_count(), 0u);
}

TEST(PlyParse, BinaryLittleEndian) {
    const auto m = parse_mesh(file(kTriangleLeHeader, triangle_body()), MeshFormat::kPly);
    ASSERT_TRUE(m.ok()) << m.error().message;
    EXPECT_EQ(m->positions, (std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0}));
    EXPECT_EQ(m->indices, (std::vector<uint32_t>{0, 1, 2}));
}

TEST(PlyParse, BinaryBigEndianMixedTypesAndSkippedLists) {
    Body b(true);
    // vertex: double x, short y, list ushort uchar junk, uint z, char c
    b.put(1.5)
        .put(int16_t{-2})
        .put(uint16_t{2})
        .put(uint8_t{9})
        .put(uint8_t{9})
        .put(uint32_t{7})
        .put(int8_t{-1});
    b.put(0.0).put(int16_t{0}).put(uint16_t{0}).put(uint32_t{0}).put(int8_t{0});
    b.put(-0.25).put(int16_t{300}).put(uint16_t{1}).put(uint8_t{1}).put(uint32_t{1}).put(int8_t{0});
    b.put(2.0).put(int16_t{2}).put(uint16_t{0}).put(uint32_t{2}).put(int8_t{0});
    // edge: list int ushort
    b.put(int32_t{2}).put(uint16_t{0}).put(uint16_t{1});
    // face: float area, list uint ushort vertex_indices
    b.put(1.0f)
        .put(uint32_t{4})
        .put(uint16_t{3})
        .put(uint16_t{2})
        .put(uint16_t{1})
        .put(uint16_t{0});
    const auto m = parse_mesh(
        file("ply\nformat binary_big_endian 1.0\n"
             "element vertex 4\nproperty float64 x\nproperty int16 y\n"
             "property list uint16 uint8 junk\nproperty uint32 z\nproperty int8 c\n"
             "element edge 1\nproperty list int ushort ends\n"
             "element face 1\nproperty float area\nproperty list uint ushort vertex_indices\n"
             "end_header\n",
             b),
        MeshFormat::kPly);
    ASSERT_TRUE(m.ok()) << m.error().message;
    EXPECT_EQ(m->positions, (std::vector<float>{1.5f, -2, 7, 0, 0, 0, -0.25f, 300, 1, 2, 2, 2}));
    EXPECT_EQ(m->indices, (std::vector<uint32_t>{3, 2, 1, 3, 1, 0}));
}

TEST(PlyParse, BinaryToleratesTrailingNewline) {
    auto data = file(kTriangleLeHeader, triangle_body());
    data.push_back(std::byte{'\n'});
    EXPECT_TRUE(parse_mesh(data, MeshFormat::kPly).ok());
}

TEST(PlyParse, HeaderWithManyElementsParses) {
    // 200k skipped elements: header handling must stay linear in the header size.
    std::string text = "ply\nformat ascii 1.0\n";
    for (int i = 0; i < 200000; ++i) text += "element e" + std::to_string(i) + " 0\n";
    text +=
        "element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 "
        "3\n";
    const Mesh m = parse_ok(text, MeshFormat::kPly);
    EXPECT_EQ(m.positions, (std::vector<float>{1, 2, 3}));
}

// ---- malformed headers (errors name the header line) ----

TEST(PlyMalformed, NotAPlyFile) {
    for (std::string_view text : {"plx\nformat ascii 1.0\n", "", "PLY\n", " ply x\n"}) {
        const auto e = parse_error(text, MeshFormat::kPly);
        EXPECT_EQ(e.line, 1u) << text;
        EXPECT_THAT(e.message, HasSubstr("not a PLY file")) << text;
    }
}

TEST(PlyMalformed, UnknownFormat) {
    const auto e =
        parse_error("ply\nformat binary_middle_endian 1.0\nend_header\n", MeshFormat::kPly);
    EXPECT_EQ(e.line, 2u);
    EXPECT_EQ(e.message,
              "line 2: unknown PLY format 'binary_middle_endian' (expected ascii, "
              "binary_little_endian or "
              "binary_big_endian)");
    EXPECT_THAT(parse_error("ply\nformat ascii 2.0\nend_header\n", MeshFormat::kPly).message,
                HasSubstr("unsupported PLY version '2.0'"));
    EXPECT_THAT(parse_error("ply\ncomment x\nend_header\n", MeshFormat::kPly).message,
                HasSubstr("line 3: bad header: no 'format' line"));
    EXPECT_THAT(parse_error("ply\nformat ascii 1.0\nformat ascii 1.0\n", MeshFormat::kPly).message,
                HasSubstr("line 3: bad header: second 'format' line"));
}

TEST(PlyMalformed, UnknownTypeNamesTheLine) {
    auto e =
        parse_error("ply\nformat ascii 1.0\nelement vertex 1\nproperty float16 x\nend_header\n",
                    MeshFormat::kPly);
    EXPECT_EQ(e.line, 4u);
    EXPECT_EQ(e.message, "line 4: unknown PLY type 'float16'");
    e = parse_error(
        "ply\nformat ascii 1.0\nelement face 1\nproperty list float int "
        "vertex_indices\nend_header\n",
        MeshFormat::kPly);
    EXPECT_EQ(e.line, 4u);
    EXPECT_THAT(e.message, HasSubstr("list count type 'float' is not an integer type"));
    e = parse_error(
        "ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int128 "
        "vertex_indices\nend_header\n",
        MeshFormat::kPly);
    EXPECT_THAT(e.message, HasSubstr(errors::kUnknownPlyType));
}

TEST(PlyMalformed, HeaderStructure) {
    auto e = parse_error("ply\nformat ascii 1.0\nproperty float x\nend_header\n", MeshFormat::kPly);
    EXPECT_EQ(e.line, 3u);
    EXPECT_THAT(e.message, HasSubstr("property before any element"));
    e = parse_error("ply\nformat ascii 1.0\nelement vertex -1\nend_header\n", MeshFormat::kPly);
    EXPECT_EQ(e.line, 3u);
    EXPECT_THAT(e.message, HasSubstr("expected 'element <name> <count>'"));
    {
        // An unknown header keyword is skipped with a warning (exporters write such lines).
        const std::string text = "ply\nformat ascii 1.0\nelemental vertex 1\nend_header\n";
        std::vector<std::string> warnings;
        MeshLimits limits;
        limits.warnings = &warnings;
        const auto* p = reinterpret_cast<const std::byte*>(text.data());
        auto mesh = parse_mesh({p, text.size()}, MeshFormat::kPly, limits);
        ASSERT_TRUE(mesh);
        EXPECT_EQ(mesh->triangle_count(), 0u);
        ASSERT_EQ(warnings.size(), 1u);
        EXPECT_THAT(warnings[0], HasSubstr("line 3: PLY header line with unknown keyword"));
    }
    e = parse_error("ply\nformat ascii 1.0\nelement vertex 0\nelement vertex 0\nend_header\n",
                    MeshFormat::kPly);
    EXPECT_THAT(e.message, HasSubstr("line 4: bad header: second element 'vertex'"));
    e = parse_error("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x y\nend_header\n",
                    MeshFormat::kPly);
    EXPECT_EQ(e.line, 4u);
}

TEST(PlyMalformed, MissingEndHeader) {
    const auto e = parse_error("ply\nformat ascii 1.0\nelement vertex 0\n", MeshFormat::kPly);
    EXPECT_EQ(e.line, 4u);
    EXPECT_THAT(e.message, HasSubstr(errors::kMissingEndHeader));
}

TEST(PlyMalformed, MissingOrMistypedMeshProperties) {
    auto e = parse_error(
        "ply\nformat ascii 1.0\ncomment\nelement vertex 1\nproperty float x\nproperty float y\n"
        "end_header\n1 2\n",
        MeshFormat::kPly);
    EXPECT_EQ(e.line, 4u);
    EXPECT_EQ(e.message, "line 4: element vertex has no property 'z'");
    e = parse_error(
        "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty "
        "float z\n"
        "element face 1\nproperty list uchar int indices\nend_header\n3 0 0 0\n",
        MeshFormat::kPly);
    EXPECT_EQ(e.line, 7u);
    EXPECT_THAT(e.message, HasSubstr("element face " + std::string(errors::kMissingProperty) +
                                     " 'vertex_indices'"));
    e = parse_error(
        "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty "
        "float z\n"
        "element face 1\nproperty int vertex_indices\nend_header\n3\n",
        MeshFormat::kPly);
    EXPECT_EQ(e.line, 8u);
    EXPECT_THAT(e.message, HasSubstr("is not a list"));
    e = parse_error(
        "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty "
        "float z\n"
        "element face 1\nproperty list uchar float vertex_indices\nend_header\n3 0 0 0\n",
        MeshFormat::kPly);
    EXPECT_THAT(e.message, HasSubstr("non-integer item type"));
    e = parse_error(
        "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty list uchar float y\n"
        "property float z\nend_header\n",
        MeshFormat::kPly);
    EXPECT_EQ(e.line, 5u);
    EXPECT_THAT(e.message, HasSubstr("vertex property 'y' is a list"));
}

TEST(PlyMalformed, CountsOverTheLimitNameTheElementLine) {
    auto e = parse_error(
        "ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n",
        MeshFormat::kPly);
    EXPECT_EQ(e.line, 3u);
    EXPECT_THAT(e.message,
                HasSubstr("vertex count 4000000000 " + std::string(errors::kLimitExceeded)));
    e = parse_error("ply\nformat ascii 1.0\nelement face 18446744073709551615\nend_header\n",
                    MeshFormat::kPly);
    EXPECT_EQ(e.line, 3u);
    EXPECT_THAT(e.message, HasSubstr("face count 18446744073709551615 exceeds the limit"));
}

// ---- malformed ascii bodies (errors name the line) ----

constexpr std::string_view kAsciiHeader =
    "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float "
    "z\n"
    "element face 1\nproperty list uchar int vertex_indices\nend_header\n";  // 9 lines

TEST(PlyMalformedAscii, BadNumber) {
    const auto e = parse_error(std::string(kAsciiHeader) + "0 0 0\n1 0 0\n0 1e 0\n3 0 1 2\n",
                               MeshFormat::kPly);
    EXPECT_EQ(e.line, 12u);
    EXPECT_EQ(e.message, "line 12: vertex 2 coordinate y '1e' is not a number");
}

TEST(PlyMalformedAscii, NanCoordinate) {
    const auto e = parse_error(std::string(kAsciiHeader) + "0 0 0\n1 0 inf\n0 1 0\n3 0 1 2\n",
                               MeshFormat::kPly);
    EXPECT_EQ(e.line, 11u);
    EXPECT_THAT(e.message,
                HasSubstr("vertex 1 coordinate z 'inf' " + std::string(errors::kNonFinite)));
}

TEST(PlyMalformedAscii, IndexOutOfRange) {
    const auto e =
        parse_error(std::string(kAsciiHeader) + "0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n", MeshFormat::kPly);
    EXPECT_EQ(e.line, 13u);
    EXPECT_EQ(e.message, "line 13: face 0 index 3 out of range (mesh has 3 vertices)");
    EXPECT_THAT(
        parse_error(std::string(kAsciiHeader) + "0 0 0\n1 0 0\n0 1 0\n3 0 -1 2\n", MeshFormat::kPly)
            .message,
        HasSubstr("index -1 out of range"));
}

TEST(PlyMalformedAscii, Truncated) {
    const auto e =
        parse_error(std::string(kAsciiHeader) + "0 0 0\n1 0 0\n0 1 0\n3 0 1", MeshFormat::kPly);
    EXPECT_EQ(e.line, 13u);
    EXPECT_THAT(e.message,
                HasSubstr(std::string(errors::kUnexpectedEnd) + " in element 'face' item 0 of 1"));
}

TEST(PlyMalformedAscii, CornerCountsAndTrailingData) {
    auto e =
        parse_error(std::string(kAsciiHeader) + "0 0 0\n1 0 0\n0 1 0\n2 0 1\n", MeshFormat::kPly);
    EXPECT_EQ(e.line, 13u);
    EXPECT_THAT(e.message,
                HasSubstr("face 0 has 2 vertices, a face " + std::string(errors::kTooFewCorners)));
    e = parse_error(std::string(kAsciiHeader) + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n\n7\n",
                    MeshFormat::kPly);
    EXPECT_EQ(e.line, 15u);
    EXPECT_THAT(e.message,
                HasSubstr(std::string(errors::kTrailingData) + " the last element: '7'"));
    e = parse_error(std::string(kAsciiHeader) + "0 0 0\n1 0 0\n0 1 0\nx 0 1 2\n", MeshFormat::kPly);
    EXPECT_THAT(e.message, HasSubstr("list length 'x' is not a non-negative integer"));
    MeshLimits limits;
    limits.max_polygon_vertices = 3;
    e = parse_error(std::string(kAsciiHeader) + "0 0 0\n1 0 0\n0 1 0\n4 0 1 2 0\n",
                    MeshFormat::kPly, limits);
    EXPECT_THAT(e.message, HasSubstr(errors::kTooManyCorners));
}

// ---- malformed binary bodies (errors name the byte offset) ----

TEST(PlyMalformedBinary, TruncatedInsideVertex) {
    auto data = file(kTriangleLeHeader, triangle_body());
    const size_t body = kTriangleLeHeader.size();
    data.resize(body + 20);  // vertex 1 ends after its y
    const auto e = parse_error(data, MeshFormat::kPly);
    EXPECT_EQ(e.byte_offset, body + 20);
    EXPECT_EQ(
        e.message,
        "byte " + std::to_string(body + 20) +
            ": file ends inside element 'vertex' item 1 of 3 (property 'z' needs 4 bytes, 0 left)");
}

TEST(PlyMalformedBinary, TruncatedInsideFaceList) {
    auto data = file(kTriangleLeHeader, triangle_body());
    const size_t body = kTriangleLeHeader.size();
    data.resize(data.size() - 4);
    const auto e = parse_error(data, MeshFormat::kPly);
    EXPECT_EQ(e.byte_offset, body + 37);
    EXPECT_THAT(e.message,
                HasSubstr(std::string(errors::kTruncated) + " element 'face' item 0 of 1"));
    EXPECT_THAT(e.message, HasSubstr("needs 12 bytes, 8 left"));
}

TEST(PlyMalformedBinary, NanCoordinate) {
    Body b(false);
    b.put(0.0f)
        .put(0.0f)
        .put(0.0f)
        .put(1.0f)
        .put(0.0f)
        .put(0.0f)
        .put(std::nanf(""))
        .put(1.0f)
        .put(0.0f);
    b.put(uint8_t{3}).put(int32_t{0}).put(int32_t{1}).put(int32_t{2});
    const auto e = parse_error(file(kTriangleLeHeader, b), MeshFormat::kPly);
    EXPECT_EQ(e.byte_offset, kTriangleLeHeader.size() + 24);
    EXPECT_THAT(e.message,
                HasSubstr("vertex 2 coordinate x (NaN) " + std::string(errors::kNonFinite)));
}

TEST(PlyMalformedBinary, IndexOutOfRangeAndNegativeListLength) {
    Body b = triangle_body();
    auto data = file(kTriangleLeHeader, b);
    const size_t body = kTriangleLeHeader.size();
    data[body + 37 + 8] = std::byte{3};  // third index: 2 -> 3
    auto e = parse_error(data, MeshFormat::kPly);
    EXPECT_EQ(e.byte_offset, body + 45);
    EXPECT_THAT(e.message, HasSubstr("face 0 index 3 out of range (mesh has 3 vertices)"));

    std::string header(kTriangleLeHeader);
    header.replace(header.find("list uchar"), 10, "list char ");
    data = file(header, triangle_body());
    data[header.size() + 36] = std::byte{0xFF};  // count -1
    e = parse_error(data, MeshFormat::kPly);
    EXPECT_EQ(e.byte_offset, header.size() + 36);
    EXPECT_THAT(e.message, HasSubstr("list length -1 is negative"));
}

TEST(PlyMalformedBinary, TrailingBytes) {
    auto data = file(kTriangleLeHeader, triangle_body());
    const size_t end = data.size();
    data.push_back(std::byte{'\n'});
    data.push_back(std::byte{0x42});
    const auto e = parse_error(data, MeshFormat::kPly);
    EXPECT_EQ(e.byte_offset, end + 1);
    EXPECT_THAT(e.message, HasSubstr(errors::kTrailingData));
}

TEST(PlyMalformedBinary, HugeCountWithLittleDataFailsWithoutHugeAllocation) {
    // 200 million vertices fit the limit, but 12 bytes are present: reserve is bounded by the
    // bytes left, and reading stops at the first missing value.
    const std::string header =
        "ply\nformat binary_little_endian 1.0\nelement vertex 200000000\nproperty float "
        "x\nproperty float y\n"
        "property float z\nend_header\n";
    Body b(false);
    b.put(1.0f).put(2.0f).put(3.0f);
    const auto e = parse_error(file(header, b), MeshFormat::kPly);
    EXPECT_EQ(e.byte_offset, header.size() + 12);
    EXPECT_THAT(e.message, HasSubstr("item 1 of 200000000"));
}

}  // namespace
}  // namespace kdrt::proto
