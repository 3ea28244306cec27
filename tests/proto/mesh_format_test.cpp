// Format names and extensions, load_mesh_file, ParseError formatting.

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "kdrt/proto/errors.h"
#include "kdrt/proto/mesh_io.h"
#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

using ::testing::HasSubstr;

TEST(MeshFormat, NamesRoundTrip) {
    for (MeshFormat f : {MeshFormat::kObj, MeshFormat::kPly, MeshFormat::kOff, MeshFormat::kStl,
                         MeshFormat::kRaw}) {
        EXPECT_EQ(mesh_format_from_name(mesh_format_name(f)), f);
    }
    EXPECT_EQ(mesh_format_name(MeshFormat::kObj), "obj");
    EXPECT_EQ(mesh_format_name(MeshFormat::kRaw), "raw");
    EXPECT_FALSE(mesh_format_from_name("OBJ").has_value());
    EXPECT_FALSE(mesh_format_from_name("gltf").has_value());
    EXPECT_FALSE(mesh_format_from_name("").has_value());
}

TEST(MeshFormat, FromPathIsCaseInsensitive) {
    EXPECT_EQ(mesh_format_from_path("a/b/bunny.OFF"), MeshFormat::kOff);
    EXPECT_EQ(mesh_format_from_path("x.Obj"), MeshFormat::kObj);
    EXPECT_EQ(mesh_format_from_path("x.ply"), MeshFormat::kPly);
    EXPECT_EQ(mesh_format_from_path("x.StL"), MeshFormat::kStl);
    EXPECT_EQ(mesh_format_from_path("x.raw"), MeshFormat::kRaw);
    EXPECT_EQ(mesh_format_from_path("x.KDRTMESH"), MeshFormat::kRaw);
    EXPECT_FALSE(mesh_format_from_path("x.off.gz").has_value());
    EXPECT_FALSE(mesh_format_from_path("off").has_value());
    EXPECT_FALSE(mesh_format_from_path("x.").has_value());
}

TEST(MeshFormat, LoadsBunny) {
    const auto mesh = load_mesh_file(test::test_data("bunny00.off"));
    ASSERT_TRUE(mesh.ok()) << mesh.error().to_string();
    EXPECT_EQ(mesh->vertex_count(), 37706u);
    EXPECT_EQ(mesh->triangle_count(), 75408u);
    test::expect_well_formed(*mesh);
    // First vertex and last face as in the file ("-0.167662 -0.411917 -0.0732205", "3  37478 37477
    // 5564").
    EXPECT_EQ(mesh->positions[0], -0.167662f);
    EXPECT_EQ(mesh->positions[1], -0.411917f);
    EXPECT_EQ(mesh->positions[2], -0.0732205f);
    EXPECT_EQ(mesh->indices[3 * 75407], 37478u);
    EXPECT_EQ(mesh->indices[3 * 75407 + 1], 37477u);
    EXPECT_EQ(mesh->indices[3 * 75407 + 2], 5564u);
}

TEST(MeshFormat, LoadsOtherTestMeshes) {
    const auto dragon = load_mesh_file(test::test_data("ChineseDragon-10kv.off"));
    ASSERT_TRUE(dragon.ok()) << dragon.error().to_string();
    EXPECT_EQ(dragon->vertex_count(), 10000u);
    EXPECT_EQ(dragon->triangle_count(), 19994u);
    const auto dino = load_mesh_file(test::test_data("diplodocus.off"));
    ASSERT_TRUE(dino.ok()) << dino.error().to_string();
    EXPECT_EQ(dino->vertex_count(), 23982u);
    EXPECT_EQ(dino->triangle_count(), 47960u);
}

TEST(MeshFormat, LoadErrorsNameThePath) {
    auto r = load_mesh_file("/nonexistent/dir/model.obj");
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.error().source, "/nonexistent/dir/model.obj");
    EXPECT_THAT(r.error().message, HasSubstr("\"/nonexistent/dir/model.obj\""));
    EXPECT_THAT(r.error().message, HasSubstr("No such file or directory"));

    r = load_mesh_file("/some/where/model.gltf");
    ASSERT_FALSE(r.ok());
    EXPECT_THAT(r.error().message, HasSubstr(errors::kUnknownExtension));
    EXPECT_THAT(r.error().message, HasSubstr("/some/where/model.gltf"));

    // An explicit format overrides the extension (and a parse error carries the path).
    r = load_mesh_file(test::test_data("bunny00.off"), MeshFormat::kObj);
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.error().line, 1u);
    EXPECT_EQ(r.error().to_string(),
              test::test_data("bunny00.off").string() + ": " + r.error().message);
    EXPECT_THAT(r.error().message, HasSubstr(errors::kUnknownStatement));
}

TEST(MeshFormat, ParseErrorToStringWithoutSource) {
    ParseError e;
    e.message = "line 3: oops";
    EXPECT_EQ(e.to_string(), "line 3: oops");
    e.source = "m.obj";
    EXPECT_EQ(e.to_string(), "m.obj: line 3: oops");
}

TEST(MeshFormat, WriterRefusesMalformedMeshes) {
    EXPECT_THROW((void)write_mesh(test::make_mesh({0, 0, 0, 1}, {}), MeshFormat::kObj),
                 std::invalid_argument);
    EXPECT_THROW((void)write_mesh(test::make_mesh({0, 0, 0}, {0, 0}), MeshFormat::kOff),
                 std::invalid_argument);
    EXPECT_THROW((void)write_mesh(test::make_mesh({0, 0, 0}, {0, 0, 1}), MeshFormat::kStl),
                 std::invalid_argument);
}

}  // namespace
}  // namespace kdrt::proto
