// The kdrt raw mesh (application/x-kdrt-mesh), little-endian:
//   u32 vertex_count, u32 triangle_count, f32 x y z per vertex, u32 i0 i1 i2 per triangle.
// The size must be exactly 8 + 12 * vertex_count + 12 * triangle_count.

#include <cstring>
#include <string>

#include "byte_io.h"
#include "mesh_common.h"

namespace kdrt::proto::detail {

Result<Mesh, ParseError> parse_raw(std::span<const std::byte> data, const MeshLimits& limits) {
    constexpr size_t kHeaderBytes = 8;
    const size_t size = data.size();
    if (size < kHeaderBytes) {
        return Err{byte_error(0, std::string(errors::kTruncated) + " the 8-byte raw mesh header (" +
                                     std::to_string(size) + " bytes)")};
    }
    const uint64_t vertex_count = load_le32(data.data());
    const uint64_t triangle_count = load_le32(data.data() + 4);
    if (vertex_count > vertex_limit(limits))
        return Err{byte_error(0, limit_message("vertex", vertex_count, vertex_limit(limits)))};
    if (triangle_count > limits.max_triangles) {
        return Err{byte_error(4, limit_message("triangle", triangle_count, limits.max_triangles))};
    }
    const uint64_t index_offset = kHeaderBytes + 12 * vertex_count;
    const uint64_t expected = index_offset + 12 * triangle_count;
    if (size != expected) {
        const std::string story =
            "header says " + std::to_string(vertex_count) + " vertices and " +
            std::to_string(triangle_count) + " triangles (" + std::to_string(expected) +
            " bytes) " + std::string(errors::kSizeMismatch) + " " + std::to_string(size) + " bytes";
        if (size > expected)
            return Err{byte_error(
                expected, std::string(errors::kTrailingData) + " the last triangle: " + story)};
        const uint64_t at = size < index_offset ? kHeaderBytes + (size - kHeaderBytes) / 12 * 12
                                                : index_offset + (size - index_offset) / 12 * 12;
        const std::string item = size < index_offset
                                     ? "vertex " + std::to_string((at - kHeaderBytes) / 12)
                                     : "triangle " + std::to_string((at - index_offset) / 12);
        return Err{byte_error(at, std::string(errors::kTruncated) + " " + item + ": " + story)};
    }

    Mesh mesh;
    mesh.positions.resize(3 * vertex_count);
    mesh.indices.resize(3 * triangle_count);
    const std::byte* src = data.data() + kHeaderBytes;
    // The file is little-endian, like every host kdrt builds for (byte_io.h asserts it).
    if (vertex_count != 0) std::memcpy(mesh.positions.data(), src, 12 * vertex_count);
    if (triangle_count != 0)
        std::memcpy(mesh.indices.data(), src + 12 * vertex_count, 12 * triangle_count);
    for (uint64_t i = 0; i < mesh.positions.size(); ++i) {
        const float value = mesh.positions[i];
        if (!std::isfinite(value)) {
            return Err{byte_error(kHeaderBytes + 4 * i, "vertex " + std::to_string(i / 3) +
                                                            " coordinate " +
                                                            axis_name(static_cast<int>(i % 3)) +
                                                            " (" + non_finite_name(value) + ") " +
                                                            std::string(errors::kNonFinite))};
        }
    }
    for (uint64_t i = 0; i < mesh.indices.size(); ++i) {
        if (mesh.indices[i] >= vertex_count) {
            return Err{byte_error(index_offset + 4 * i,
                                  "triangle " + std::to_string(i / 3) + " index " +
                                      std::to_string(mesh.indices[i]) + " " +
                                      std::string(errors::kIndexOutOfRange) + " (mesh has " +
                                      std::to_string(vertex_count) + " vertices)")};
        }
    }
    return mesh;
}

}  // namespace kdrt::proto::detail
