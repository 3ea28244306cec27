#pragma once
// Helpers shared by the proto tests.

#include <gtest/gtest.h>

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <initializer_list>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/mesh.h"
#include "kdrt/proto/mesh_io.h"

namespace kdrt::proto::test {

inline std::vector<std::byte> bytes_of(std::string_view text) {
    std::vector<std::byte> out(text.size());
    if (!text.empty()) std::memcpy(out.data(), text.data(), text.size());
    return out;
}

/// Bytes from a hex dump: pairs of hex digits; blanks, newlines and "|" are separators.
inline std::vector<std::byte> from_hex(std::string_view dump) {
    std::vector<std::byte> out;
    int high = -1;
    for (char c : dump) {
        int nibble = -1;
        if (c >= '0' && c <= '9') nibble = c - '0';
        if (c >= 'a' && c <= 'f') nibble = c - 'a' + 10;
        if (c >= 'A' && c <= 'F') nibble = c - 'A' + 10;
        if (nibble < 0) {
            EXPECT_TRUE(c == ' ' || c == '\n' || c == '|')
                << "bad hex dump character '" << c << "'";
            EXPECT_EQ(high, -1) << "odd number of hex digits in a byte";
            continue;
        }
        if (high < 0) {
            high = nibble;
        } else {
            out.push_back(static_cast<std::byte>(high * 16 + nibble));
            high = -1;
        }
    }
    EXPECT_EQ(high, -1) << "dangling hex digit";
    return out;
}

inline void append_le32(std::vector<std::byte>& out, uint32_t v) {
    for (int i = 0; i < 4; ++i) out.push_back(static_cast<std::byte>((v >> (8 * i)) & 0xFF));
}

inline void append_le_f32(std::vector<std::byte>& out, float f) {
    uint32_t bits = 0;
    std::memcpy(&bits, &f, 4);
    append_le32(out, bits);
}

/// KDRT_TEST_SEED, or a fixed default.
inline uint64_t test_seed() {
    const char* env = std::getenv("KDRT_TEST_SEED");
    return env != nullptr ? std::strtoull(env, nullptr, 10) : 20240601u;
}

inline std::filesystem::path test_data(std::string_view name) {
    return std::filesystem::path(KDRT_TEST_DATA_DIR) / name;
}

/// A parsed mesh is always well-formed: whole vertices and triangles, finite coordinates,
/// in-range indices.
inline void expect_well_formed(const Mesh& mesh) {
    ASSERT_EQ(mesh.positions.size() % 3, 0u);
    ASSERT_EQ(mesh.indices.size() % 3, 0u);
    for (float f : mesh.positions) ASSERT_TRUE(std::isfinite(f));
    for (uint32_t i : mesh.indices) ASSERT_LT(i, mesh.vertex_count());
}

/// A mesh from flat position and index lists.
inline Mesh make_mesh(std::initializer_list<float> positions,
                      std::initializer_list<uint32_t> indices) {
    Mesh m;
    m.positions = positions;
    m.indices = indices;
    return m;
}

/// Parses text in `format`, failing the test on error.
inline Mesh parse_ok(std::string_view text, MeshFormat format, const MeshLimits& limits = {}) {
    auto result = parse_mesh(bytes_of(text), format, limits);
    EXPECT_TRUE(result.ok()) << (result.ok() ? "" : result.error().message);
    return result.ok() ? std::move(result).value() : Mesh{};
}

/// Parses `data` in `format` expecting an error; returns it (empty message if it parsed).
inline ParseError parse_error(std::span<const std::byte> data, MeshFormat format,
                              const MeshLimits& limits = {}) {
    auto result = parse_mesh(data, format, limits);
    EXPECT_FALSE(result.ok()) << "parsed although an error was expected";
    return result.ok() ? ParseError{} : std::move(result).error();
}

inline ParseError parse_error(std::string_view text, MeshFormat format,
                              const MeshLimits& limits = {}) {
    return parse_error(bytes_of(text), format, limits);
}

/// A small closed mesh (tetrahedron) used by several tests.
inline Mesh tetrahedron() {
    return make_mesh({0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1.5f}, {0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3});
}

}  // namespace kdrt::proto::test
