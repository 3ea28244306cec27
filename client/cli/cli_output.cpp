#include "cli_output.h"

#include <cstdio>

#include "kdrt/proto/json_api.h"

namespace kdrt::cli {
namespace {

std::string pad_right(std::string text, size_t width) {
    if (text.size() < width) text.append(width - text.size(), ' ');
    return text;
}

std::string pad_left(const std::string& text, size_t width) {
    return text.size() < width ? std::string(width - text.size(), ' ') + text : text;
}

std::string vec3_text(Vec3 v) {
    std::string out = "[";  // appended: GCC 12 warns falsely (-Wrestrict) on "[" + std::string
    out += fixed(v.x, 6);
    out += ", ";
    out += fixed(v.y, 6);
    out += ", ";
    out += fixed(v.z, 6);
    out += "]";
    return out;
}

}  // namespace

std::string fixed(double value, int decimals) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.*f", decimals, value);
    return buf;
}

std::string upload_line(const MeshInfo& mesh, std::string_view file) {
    return mesh.id + "  " + std::to_string(mesh.triangles) + " triangles  " +
           fixed(mesh.tree.build_ms, 1) + " ms  " + std::string(file);
}

std::string mesh_table(std::span<const MeshInfo> meshes) {
    std::string out = pad_right("ID", 66) + pad_left("TRIANGLES", 11) + pad_left("VERTICES", 11) +
                      pad_left("BUILD_MS", 10) + "  IN_MEMORY\n";
    for (const MeshInfo& m : meshes) {
        out += pad_right(m.id, 66) + pad_left(std::to_string(m.triangles), 11) +
               pad_left(std::to_string(m.vertices), 11) + pad_left(fixed(m.tree.build_ms, 1), 10) +
               "  " + (m.in_memory ? (*m.in_memory ? "yes" : "no") : "-") + "\n";
    }
    return out;
}

std::string mesh_details(const MeshInfo& m) {
    const TreeStats& t = m.tree;
    std::string out;
    out += "id          " + m.id + "\n";
    out += "triangles   " + std::to_string(m.triangles) + "\n";
    out += "vertices    " + std::to_string(m.vertices) + "\n";
    out += "bounds      " + vec3_text(m.bounds.lo) + " .. " + vec3_text(m.bounds.hi) + "\n";
    out += "build_ms    " + fixed(t.build_ms, 1) + "\n";
    out += "tree        " + std::to_string(t.nodes) + " nodes, " + std::to_string(t.leaves) +
           " leaves (" + std::to_string(t.empty_leaves) + " empty), " + std::to_string(t.refs) +
           " refs, max depth " + std::to_string(t.max_depth) + ", " +
           fixed(t.mean_tris_per_leaf, 2) + " triangles per leaf\n";
    out += "sah_cost    " + fixed(t.sah_cost, 2) + "\n";
    out += "bytes       " + std::to_string(t.bytes) + " (" + fixed(t.bytes_per_triangle, 1) +
           " per triangle)\n";
    if (m.in_memory) out += std::string("in_memory   ") + (*m.in_memory ? "yes" : "no") + "\n";
    return out;
}

std::string mesh_json_line(const MeshInfo& mesh, std::string_view file) {
    std::string summary = proto::encode_mesh_summary(mesh);
    if (file.empty()) return summary;
    const proto::JsonField fields[] = {{"file", file}};
    std::string head = proto::encode_flat_object(fields);
    // Two JSON objects joined: {"file":...} without its '}' + the summary without its '{'.
    head.pop_back();
    return head + "," + summary.substr(1);
}

}  // namespace kdrt::cli
