// proto/openapi.yaml must document every route the server registers and every problem type it
// can answer with (a text check; the document itself is validated with openapi-spec-validator).

#include <gtest/gtest.h>

#include "kdrt/proto/file_io.h"
#include "kdrt/proto/problem.h"

namespace kdrt::proto {
namespace {

std::string read_openapi() {
    auto bytes = read_file_bytes(std::string(KDRT_SOURCE_DIR) + "/proto/openapi.yaml");
    EXPECT_TRUE(bytes) << bytes.error();
    return bytes ? std::string(reinterpret_cast<const char*>(bytes->data()), bytes->size())
                 : std::string();
}

TEST(OpenApi, DocumentsEveryRoute) {
    const std::string doc = read_openapi();
    EXPECT_EQ(doc.rfind("openapi: 3.1.0\n", 0), 0u);
    for (const char* path :
         {"/v1/meshes", "/v1/meshes/{id}", "/v1/meshes/{id}/intersect",
          "/v1/meshes/{id}/intersect_all", "/v1/render", "/v1/jobs/{id}", "/v1/jobs/{id}/result",
          "/healthz", "/readyz", "/metrics", "/v1/scenes", "/v1/scenes/{id}",
          "/v1/scenes/{id}/poses", "/v1/scenes/{id}/instances", "/v1/scenes/{id}/intersect",
          "/v1/scenes/{id}/intersect_all", "/v1/scenes/{id}/distance", "/v1/scenes/{id}/scan"})
        EXPECT_NE(doc.find("\n  " + std::string(path) + ":\n"), std::string::npos) << path;
    for (const char* media :
         {"model/obj", "model/stl", "application/ply", "application/x-off",
          "application/x-kdrt-mesh", "application/x-kdrt-rays", "application/x-kdrt-hits",
          "application/x-kdrt-occlusion", "application/x-kdrt-multi-hits",
          "application/x-kdrt-hit-counts", "application/problem+json", "image/png", "image/x-exr",
          "application/x-kdrt-poses"})
        EXPECT_NE(doc.find(media), std::string::npos) << media;
}

TEST(OpenApi, DocumentsEveryProblemType) {
    const std::string doc = read_openapi();
    for (int k = 0; k <= static_cast<int>(kLastProblemKind); ++k) {
        const auto kind = static_cast<ProblemKind>(k);
        const std::string type(problem_type(kind));
        EXPECT_NE(doc.find("- " + type + "\n"), std::string::npos) << type;
        const std::string slug = type.substr(type.rfind(':') + 1);
        EXPECT_NE(doc.find(slug + " " + std::to_string(problem_status(kind))), std::string::npos)
            << slug << " " << problem_status(kind);
    }
}

}  // namespace
}  // namespace kdrt::proto
