#pragma once
/// Content-derived mesh ids. A mesh id is the SHA-256 (lower-case hex, 64 characters) of the
/// mesh's canonical triangle list: per triangle, in triangle order, its three corner positions
/// as 9 little-endian f32 (36 bytes per triangle). Vertex sharing, vertex order and the file
/// format do not matter: the same triangles give the same id whether uploaded as OBJ, PLY, OFF,
/// STL or raw. Coordinates are compared bit for bit (-0.0 and 0.0 differ).

#include <cstddef>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/mesh_types.h"

namespace kdrt::proto {

/// Length of a mesh id in characters.
inline constexpr size_t kMeshIdLength = 64;
/// Bytes per triangle in the canonical triangle list.
inline constexpr size_t kCanonicalTriangleBytes = 36;

/// The canonical triangle list of `mesh` (triangle_count() * 36 bytes). Precondition: every
/// index is < vertex_count() (any mesh from parse_mesh); otherwise std::invalid_argument.
[[nodiscard]] std::vector<std::byte> canonical_triangles(const Mesh& mesh);

/// SHA-256 of canonical_triangles(mesh), lower-case hex, computed in fixed-size blocks without
/// materialising the list. Same precondition. Thread-safe.
[[nodiscard]] std::string mesh_id(const Mesh& mesh);

/// SHA-256 of `data`, lower-case hex.
[[nodiscard]] std::string sha256_hex(std::span<const std::byte> data);

/// True when `text` has the form of a mesh id: exactly 64 characters 0-9 a-f. Inline: kdrt::proto
/// (the scene files) checks ids too, and links neither kdrt::proto_json nor OpenSSL.
[[nodiscard]] constexpr bool is_mesh_id(std::string_view text) noexcept {
    if (text.size() != kMeshIdLength) return false;
    for (const char c : text)
        if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
    return true;
}

}  // namespace kdrt::proto
