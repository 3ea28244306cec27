// Format names, dispatch, and loading mesh files from disk.

#include <algorithm>
#include <cctype>
#include <string>

#include "kdrt/proto/file_io.h"
#include "mesh_common.h"

namespace kdrt::proto {

std::optional<MeshFormat> mesh_format_from_name(std::string_view name) noexcept {
    if (name == "obj") return MeshFormat::kObj;
    if (name == "ply") return MeshFormat::kPly;
    if (name == "off") return MeshFormat::kOff;
    if (name == "stl") return MeshFormat::kStl;
    if (name == "raw") return MeshFormat::kRaw;
    return std::nullopt;
}

std::optional<MeshFormat> mesh_format_from_path(const std::filesystem::path& path) {
    std::string ext = path.extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    if (ext == ".kdrtmesh") return MeshFormat::kRaw;
    if (ext.size() < 2) return std::nullopt;
    return mesh_format_from_name(std::string_view(ext).substr(1));
}

std::string_view mesh_format_name(MeshFormat format) noexcept {
    switch (format) {
        case MeshFormat::kObj:
            return "obj";
        case MeshFormat::kPly:
            return "ply";
        case MeshFormat::kOff:
            return "off";
        case MeshFormat::kStl:
            return "stl";
        case MeshFormat::kRaw:
            return "raw";
    }
    return "unknown";
}

std::string ParseError::to_string() const {
    return source.empty() ? message : source + ": " + message;
}

Result<Mesh, ParseError> parse_mesh(std::span<const std::byte> data, MeshFormat format,
                                    const MeshLimits& limits) {
    switch (format) {
        case MeshFormat::kObj:
            return detail::parse_obj(detail::as_text(data), limits);
        case MeshFormat::kPly:
            return detail::parse_ply(data, limits);
        case MeshFormat::kOff:
            return detail::parse_off(detail::as_text(data), limits);
        case MeshFormat::kStl:
            return detail::parse_stl(data, limits);
        case MeshFormat::kRaw:
            return detail::parse_raw(data, limits);
    }
    ParseError error;
    error.message = "unknown mesh format " + std::to_string(static_cast<int>(format));
    return Err{std::move(error)};
}

Result<Mesh, ParseError> load_mesh_file(const std::filesystem::path& path,
                                        std::optional<MeshFormat> format,
                                        const MeshLimits& limits) {
    ParseError error;
    error.source = path.string();
    if (!format) format = mesh_format_from_path(path);
    if (!format) {
        error.message =
            std::string(errors::kUnknownExtension) + " of \"" + path.string() +
            "\" from its extension (expected .obj, .ply, .off, .stl, .raw or .kdrtmesh)";
        return Err{std::move(error)};
    }
    auto bytes = read_file_bytes(path);
    if (!bytes) {
        error.message = std::move(bytes).error();
        return Err{std::move(error)};
    }
    auto mesh = parse_mesh(*bytes, *format, limits);
    if (!mesh) mesh.error().source = path.string();
    return mesh;
}

}  // namespace kdrt::proto
