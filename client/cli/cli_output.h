#pragma once
/// How `kdrt` prints what the server reports: human lines and tables, and JSON lines whose
/// members are the server's (encoded by kdrt::proto, so the keys exist once).

#include <span>
#include <string>
#include <string_view>

#include "kdrt/client/client.h"

namespace kdrt::cli {

/// printf("%.*f").
[[nodiscard]] std::string fixed(double value, int decimals);

/// "<id>  <triangles> triangles  <build_ms> ms  <file>" (upload).
[[nodiscard]] std::string upload_line(const MeshInfo& mesh, std::string_view file);

/// The header and one row per mesh: ID, TRIANGLES, VERTICES, BUILD_MS, IN_MEMORY (meshes).
[[nodiscard]] std::string mesh_table(std::span<const MeshInfo> meshes);

/// "key  value" lines of every field of a summary (info).
[[nodiscard]] std::string mesh_details(const MeshInfo& mesh);

/// The server's JSON object of a mesh on one line; with `file`, "file" is the first member.
[[nodiscard]] std::string mesh_json_line(const MeshInfo& mesh, std::string_view file = {});

}  // namespace kdrt::cli
