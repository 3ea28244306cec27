#pragma once
/// Triangle meshes as the engine takes them: float positions and uint32 triangle indices. Value
/// types only (no function here needs kdrt_engine); kdrt/mesh.h validates meshes.

#include <cstddef>
#include <cstdint>
#include <vector>

#include "kdrt/types.h"

namespace kdrt {

/// An indexed triangle mesh. `positions` holds x,y,z per vertex; `indices` holds three vertex
/// indices per triangle. Triangle ids are positions in `indices` / 3 (input order).
struct Mesh {
    std::vector<float> positions;
    std::vector<uint32_t> indices;

    [[nodiscard]] size_t vertex_count() const noexcept { return positions.size() / 3; }
    [[nodiscard]] size_t triangle_count() const noexcept { return indices.size() / 3; }
    [[nodiscard]] Vec3 vertex(size_t i) const noexcept {
        return {positions[3 * i], positions[3 * i + 1], positions[3 * i + 2]};
    }
    /// Corner `corner` (0..2) of triangle `tri`.
    [[nodiscard]] Vec3 corner(size_t tri, int corner) const noexcept {
        return vertex(indices[3 * tri + static_cast<size_t>(corner)]);
    }
};

/// Largest triangle count: the 30-bit node fields address up to 2^30 - 1, and the single-ray
/// leaf test addresses the leaf-ordered triangles (9 floats each) by signed 32-bit float offsets
/// (one gather a pass, wide_kernel.h), which reach (2^31 - 1) / 9 = 238,609,294 triangles.
inline constexpr size_t kMaxTriangles = ((size_t{1} << 31) - 1) / 9;

}  // namespace kdrt
