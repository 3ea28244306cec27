#pragma once
// Oracles shared by the fuzz targets: a violated invariant traps, which libFuzzer and the
// standalone replay runner both report as a crash.

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <span>

#include "kdrt/proto/mesh_io.h"

namespace kdrt::fuzz {

inline void require(bool condition) {
    if (!condition) __builtin_trap();
}

inline std::span<const std::byte> as_bytes(const uint8_t* data, size_t size) {
    return {reinterpret_cast<const std::byte*>(data), size};
}

/// Parses `data` as `format`. A parsed mesh must be well-formed, and must survive a write/parse
/// round trip unchanged (STL: same triangle corners).
inline void fuzz_mesh(const uint8_t* data, size_t size, proto::MeshFormat format,
                      const proto::MeshWriteOptions& rewrite = {}) {
    const auto parsed = proto::parse_mesh(as_bytes(data, size), format);
    if (!parsed) {
        require(!parsed.error().message.empty());
        return;
    }
    const Mesh& mesh = *parsed;
    require(mesh.positions.size() % 3 == 0 && mesh.indices.size() % 3 == 0);
    for (float f : mesh.positions) require(std::isfinite(f));
    for (uint32_t i : mesh.indices) require(i < mesh.vertex_count());

    const auto bytes = proto::write_mesh(mesh, format, rewrite);
    const auto again = proto::parse_mesh(bytes, format);
    require(again.ok());
    require(again->triangle_count() == mesh.triangle_count());
    if (format == proto::MeshFormat::kStl) {
        for (size_t t = 0; t < mesh.triangle_count(); ++t) {
            for (int c = 0; c < 3; ++c) require(again->corner(t, c) == mesh.corner(t, c));
        }
    } else {
        require(again->positions == mesh.positions && again->indices == mesh.indices);
    }
}

}  // namespace kdrt::fuzz
