// The kdrt raw mesh: exact layout, malformed files with their byte offsets.

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>

#include "kdrt/proto/errors.h"
#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

using test::append_le32;
using test::append_le_f32;
using test::parse_error;
using ::testing::HasSubstr;

/// A raw file built field by field, independent of the writer.
std::vector<std::byte> raw(uint32_t vertex_count, uint32_t triangle_count,
                           const std::vector<float>& positions,
                           const std::vector<uint32_t>& indices) {
    std::vector<std::byte> out;
    append_le32(out, vertex_count);
    append_le32(out, triangle_count);
    for (float f : positions) append_le_f32(out, f);
    for (uint32_t i : indices) append_le32(out, i);
    return out;
}

const std::vector<float> kQuadPositions = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0};
const std::vector<uint32_t> kQuadIndices = {0, 1, 2, 0, 2, 3};

TEST(RawParse, ExactLayout) {
    const auto bytes = raw(4, 2, kQuadPositions, kQuadIndices);
    ASSERT_EQ(bytes.size(), 8u + 48 + 24);
    const auto m = parse_mesh(bytes, MeshFormat::kRaw);
    ASSERT_TRUE(m.ok()) << m.error().message;
    EXPECT_EQ(m->positions, kQuadPositions);
    EXPECT_EQ(m->indices, kQuadIndices);
    // The writer produces the same bytes.
    EXPECT_EQ(write_mesh(*m, MeshFormat::kRaw), bytes);
}

TEST(RawMalformed, HeaderTooShort) {
    const auto e = parse_error(std::vector<std::byte>(5), MeshFormat::kRaw);
    EXPECT_EQ(e.byte_offset, 0u);
    EXPECT_EQ(e.message, "byte 0: file ends inside the 8-byte raw mesh header (5 bytes)");
}

TEST(RawMalformed, TruncatedInsideVertices) {
    auto bytes = raw(4, 2, kQuadPositions, kQuadIndices);
    bytes.resize(8 + 12 + 7);
    const auto e = parse_error(bytes, MeshFormat::kRaw);
    EXPECT_EQ(e.byte_offset, 20u);
    EXPECT_EQ(e.message,
              "byte 20: file ends inside vertex 1: header says 4 vertices and 2 triangles (80 "
              "bytes) but the file has "
              "27 bytes");
}

TEST(RawMalformed, TruncatedInsideTriangles) {
    auto bytes = raw(4, 2, kQuadPositions, kQuadIndices);
    bytes.resize(bytes.size() - 1);
    const auto e = parse_error(bytes, MeshFormat::kRaw);
    EXPECT_EQ(e.byte_offset, 68u);
    EXPECT_THAT(e.message, HasSubstr(std::string(errors::kTruncated) + " triangle 1"));
}

TEST(RawMalformed, TrailingBytes) {
    auto bytes = raw(4, 2, kQuadPositions, kQuadIndices);
    bytes.push_back(std::byte{0});
    const auto e = parse_error(bytes, MeshFormat::kRaw);
    EXPECT_EQ(e.byte_offset, 80u);
    EXPECT_THAT(e.message, HasSubstr(errors::kTrailingData));
    EXPECT_THAT(e.message, HasSubstr("but the file has 81 bytes"));
}

TEST(RawMalformed, NanCoordinate) {
    auto positions = kQuadPositions;
    positions[7] = std::nanf("");
    const auto e = parse_error(raw(4, 2, positions, kQuadIndices), MeshFormat::kRaw);
    EXPECT_EQ(e.byte_offset, 8u + 28);
    EXPECT_EQ(e.message, "byte 36: vertex 2 coordinate y (NaN) is not finite");
}

TEST(RawMalformed, IndexOutOfRange) {
    auto indices = kQuadIndices;
    indices[4] = 4;
    const auto e = parse_error(raw(4, 2, kQuadPositions, indices), MeshFormat::kRaw);
    EXPECT_EQ(e.byte_offset, 8u + 48 + 16);
    EXPECT_EQ(e.message, "byte 72: triangle 1 index 4 out of range (mesh has 4 vertices)");
}

TEST(RawMalformed, HugeCountsWithoutAllocation) {
    // 2^32-1 vertices and triangles claimed by an 8-byte file: refused by the limit.
    auto e = parse_error(raw(0xFFFFFFFFu, 0xFFFFFFFFu, {}, {}), MeshFormat::kRaw);
    EXPECT_EQ(e.byte_offset, 0u);
    EXPECT_THAT(e.message,
                HasSubstr("vertex count 4294967295 " + std::string(errors::kLimitExceeded)));
    e = parse_error(raw(3, 0xFFFFFFFFu, {0, 0, 0, 0, 0, 0, 0, 0, 0}, {}), MeshFormat::kRaw);
    EXPECT_EQ(e.byte_offset, 4u);
    EXPECT_THAT(e.message, HasSubstr("triangle count 4294967295"));
    // Within the limits, but the size gives it away.
    e = parse_error(raw(200000000, 0, {}, {}), MeshFormat::kRaw);
    EXPECT_EQ(e.byte_offset, 8u);
    EXPECT_THAT(e.message, HasSubstr("vertex 0: header says 200000000 vertices"));
}

}  // namespace
}  // namespace kdrt::proto
