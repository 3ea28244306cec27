#include "kdrt/mesh.h"

#include <cmath>
#include <string>

namespace kdrt {

void validate_mesh(const Mesh& mesh) {
    if (mesh.positions.size() % 3 != 0) {
        throw MeshError("mesh positions: " + std::to_string(mesh.positions.size()) +
                        " floats is not a multiple of 3 (x, y, z per vertex)");
    }
    if (mesh.indices.size() % 3 != 0) {
        throw MeshError("mesh indices: " + std::to_string(mesh.indices.size()) +
                        " indices is not a multiple of 3 (three per triangle)");
    }
    if (mesh.triangle_count() > kMaxTriangles) {
        throw MeshError("mesh has " + std::to_string(mesh.triangle_count()) +
                        " triangles; at most " + std::to_string(kMaxTriangles) + " are supported");
    }
    static constexpr char kAxis[3] = {'x', 'y', 'z'};
    for (size_t i = 0; i < mesh.positions.size(); ++i) {
        const float c = mesh.positions[i];
        if (!std::isfinite(c)) {
            throw MeshError("vertex " + std::to_string(i / 3) + ": coordinate " + kAxis[i % 3] +
                            " is " + (std::isnan(c) ? "NaN" : "infinite"));
        }
    }
    const size_t vertex_count = mesh.vertex_count();
    for (size_t i = 0; i < mesh.indices.size(); ++i) {
        if (mesh.indices[i] >= vertex_count) {
            throw MeshError("triangle " + std::to_string(i / 3) + ": corner " +
                            std::to_string(i % 3) + " refers to vertex " +
                            std::to_string(mesh.indices[i]) + " but the mesh has " +
                            std::to_string(vertex_count) + " vertices");
        }
    }
}

Aabb mesh_bounds(const Mesh& mesh) noexcept {
    Aabb box;
    for (uint32_t index : mesh.indices) {
        box.extend(mesh.vertex(index));
    }
    return box;
}

}  // namespace kdrt
