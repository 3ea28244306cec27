// Files as real exporters write them (tests/data/quirks/): CRLF line ends, comments and obj_info,
// Blender 2.4x's PLY header line without "comment", OBJ vt/vn with every corner form and
// o/g/s/usemtl/mtllib/l statements, a binary STL whose header starts with "solid", PLY faces with
// extra properties. Each loads to the same one triangle (0,0,0) (1,0,0) (0,1,0).

#include <gtest/gtest.h>

#include "kdrt/proto/file_io.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/mesh_io.h"
#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

/// The triangle every quirk file holds: (0,0,0), (1,0,0), (0,1,0).
Mesh quirk_triangle() { return test::make_mesh({0, 0, 0, 1, 0, 0, 0, 1, 0}, {0, 1, 2}); }

Mesh load_quirk(const std::string& name, std::vector<std::string>* warnings = nullptr) {
    const auto path = test::test_data("quirks/" + name);
    auto bytes = read_file_bytes(path);
    EXPECT_TRUE(bytes) << path;
    if (!bytes) return {};
    auto format = mesh_format_from_path(path.string());
    EXPECT_TRUE(format) << path;
    MeshLimits limits;
    limits.warnings = warnings;
    auto mesh = parse_mesh(*bytes, *format, limits);
    EXPECT_TRUE(mesh) << name << ": " << (mesh ? "" : mesh.error().to_string());
    return mesh ? std::move(*mesh) : Mesh{};
}

TEST(MeshQuirks, EveryExporterQuirkLoadsTheSameTriangle) {
    const std::string want = mesh_id(quirk_triangle());
    for (const char* name : {"ascii_crlf.stl", "binary_solid_header.stl",
                             "crlf_objinfo_faceprops.ply", "blender247.ply"}) {
        SCOPED_TRACE(name);
        std::vector<std::string> warnings;
        const Mesh mesh = load_quirk(name, &warnings);
        EXPECT_EQ(mesh.triangle_count(), 1u);
        EXPECT_EQ(mesh_id(mesh), want);
        if (std::string(name) != "blender247.ply") {
            EXPECT_TRUE(warnings.empty());
        }
    }
    // The OBJ has the triangle four times: plain, v/vt, v//vn and v/vt/vn corners.
    const Mesh obj = load_quirk("blender_crlf.obj");
    ASSERT_EQ(obj.triangle_count(), 4u);
    for (size_t t = 0; t < 4; ++t)
        for (int c = 0; c < 3; ++c) EXPECT_EQ(obj.corner(t, c), quirk_triangle().corner(0, c));
}

TEST(MeshQuirks, BlenderCreatedByLineIsSkippedWithAWarning) {
    std::vector<std::string> warnings;
    const Mesh mesh = load_quirk("blender247.ply", &warnings);
    EXPECT_EQ(mesh.triangle_count(), 1u);
    ASSERT_EQ(warnings.size(), 1u);
    EXPECT_EQ(warnings[0], "line 3: PLY header line with unknown keyword 'Created' skipped");
    // Without a warnings sink the file still loads.
    EXPECT_EQ(load_quirk("blender247.ply").triangle_count(), 1u);
}

}  // namespace
}  // namespace kdrt::proto
