#pragma once
/// Triangle meshes as the engine takes them: float positions and uint32 triangle indices.

#include <stdexcept>

#include "kdrt/mesh_types.h"
#include "kdrt/types.h"

namespace kdrt {

/// Thrown by validate_mesh and build_kdtree for a mesh the engine cannot accept.
class MeshError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// Checks a mesh and throws MeshError naming the first problem found: positions not a multiple
/// of 3, indices not a multiple of 3, a NaN/Inf coordinate (with the vertex index and axis), an
/// index out of range (with the triangle index, corner and value), or too many triangles.
/// Degenerate (zero-area) triangles are valid: they are kept, and can never be hit.
void validate_mesh(const Mesh& mesh);

/// Bounds of all vertices referenced by triangles (empty box for a mesh without triangles).
[[nodiscard]] Aabb mesh_bounds(const Mesh& mesh) noexcept;

}  // namespace kdrt
