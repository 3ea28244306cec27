#pragma once
/// Mesh files <-> kdrt::Mesh: OBJ, PLY (ascii and binary), OFF, STL (ascii and binary) and the
/// kdrt raw mesh (application/x-kdrt-mesh). Accepted syntax and byte layouts: proto/FORMATS.md.
///
/// Parsers take untrusted bytes: they never throw (except std::bad_alloc), crash or hang, cap
/// every count with MeshLimits before allocating, and never allocate more than the remaining
/// input could justify. Every polygon with n >= 3 corners becomes the fan of n - 2 triangles
/// (v0, vi, vi+1), i = 1 .. n-2, in file order. NaN/Inf coordinates, out-of-range indices and
/// faces with fewer than 3 corners are errors. All functions are thread-safe.

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/mesh_types.h"
#include "kdrt/proto/result.h"

namespace kdrt::proto {

/// Supported mesh file formats.
enum class MeshFormat { kObj, kPly, kOff, kStl, kRaw };

/// "obj", "ply", "off", "stl", "raw" (exact, lower case) -> format; anything else -> nullopt.
[[nodiscard]] std::optional<MeshFormat> mesh_format_from_name(std::string_view name) noexcept;

/// Format from the file extension, case-insensitive: .obj .ply .off .stl, and .raw or .kdrtmesh
/// for the raw format. Unknown or missing extension -> nullopt.
[[nodiscard]] std::optional<MeshFormat> mesh_format_from_path(const std::filesystem::path& path);

/// "obj", "ply", "off", "stl" or "raw".
[[nodiscard]] std::string_view mesh_format_name(MeshFormat format) noexcept;

/// Why a mesh file was refused.
struct ParseError {
    /// What is wrong and where, location first: "line 12: face index 40000 out of range (mesh
    /// has 37706 vertices)" for text, "byte 84: file ends inside triangle 3 (expected 134 bytes,
    /// have 100)" for binary data.
    std::string message;
    /// 1-based line of the problem in text formats (and in PLY headers); 0 if not applicable.
    uint64_t line = 0;
    /// Byte offset of the problem in binary data; 0 if not applicable (or the offset is 0).
    uint64_t byte_offset = 0;
    /// The file path when the error came from load_mesh_file, else empty.
    std::string source;

    /// `message`, prefixed by `source: ` when source is set.
    [[nodiscard]] std::string to_string() const;
};

/// Caps checked before allocating. Exceeding one is a ParseError naming the count and the limit.
struct MeshLimits {
    /// Most vertices (for STL: 3 per triangle). Values above 2^32 act as 2^32 (uint32 indices).
    uint64_t max_vertices = 1ull << 28;
    /// Most triangles after fan triangulation (default: the engine's kMaxTriangles).
    uint64_t max_triangles = (1ull << 30) - 1;
    /// Most corners of one polygon (OBJ/OFF/PLY faces).
    uint32_t max_polygon_vertices = 1u << 16;
    /// When set, receives one line per thing the parser skipped that a user may want to know
    /// about (a PLY header line with an unknown keyword, e.g. Blender 2.4x's "Created by ...").
    std::vector<std::string>* warnings = nullptr;
};

/// Parses a whole file held in memory. Errors name the line (text formats, PLY header) or byte
/// offset (binary data) of the first problem.
///   OBJ: `v` and `f` statements; other standard OBJ statements are ignored, unknown ones are
///        an error. Negative (relative) indices and v, v/vt, v//vn, v/vt/vn corners.
///   PLY: ascii, binary_little_endian, binary_big_endian; x, y, z of element vertex (any scalar
///        type) and list vertex_indices / vertex_index of element face; the rest is skipped.
///        A header line with an unknown keyword is skipped with a warning (limits.warnings).
///   OFF: [ST][C][N]OFF header, one vertex per line (first 3 numbers), faces `n i0 .. in-1`.
///   STL: binary when 84 + 50 * count equals the size (even if the header starts with "solid"),
///        else ascii. Three vertices per triangle, no deduplication.
///   raw: u32 vertex count, u32 triangle count, f32 xyz each, u32 x3 each, little-endian.
[[nodiscard]] Result<Mesh, ParseError> parse_mesh(std::span<const std::byte> data,
                                                  MeshFormat format, const MeshLimits& limits = {});

/// Reads and parses a mesh file. Without `format`, it comes from the extension (an unknown one is
/// an error naming the path). Read errors name the path and the OS reason. `source` is set.
[[nodiscard]] Result<Mesh, ParseError> load_mesh_file(const std::filesystem::path& path,
                                                      std::optional<MeshFormat> format = {},
                                                      const MeshLimits& limits = {});

/// Encoding choices for write_mesh.
struct MeshWriteOptions {
    /// PLY and STL: binary (true) or ascii (false). OBJ and OFF are always ascii, raw always
    /// binary.
    bool binary = true;
    /// PLY binary only: binary_big_endian instead of binary_little_endian.
    bool big_endian = false;
};

/// Serialises a mesh. Text output writes floats in shortest round-trip form (std::to_chars), so
/// parse_mesh(write_mesh(m, f), f) returns exactly the same positions; OBJ/OFF/PLY/raw also keep
/// the indices, STL writes 3 vertices per triangle with a computed unit normal and a header that
/// does not start with "solid". Throws std::invalid_argument if the mesh is malformed
/// (positions/indices not multiples of 3, an index >= vertex_count()) or, for raw and binary
/// STL, has more than 2^32 - 1 vertices/triangles. NaN coordinates are written as "nan" / NaN
/// bits; parse_mesh then refuses them.
[[nodiscard]] std::vector<std::byte> write_mesh(const Mesh& mesh, MeshFormat format,
                                                const MeshWriteOptions& options = {});

}  // namespace kdrt::proto
