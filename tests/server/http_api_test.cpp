// API v1 happy paths against the real binary: uploads in every format, mesh listing and
// deletion, binary and JSON intersect batches compared bit for bit with the in-process engine.

#include <gtest/gtest.h>

#include <cstring>

#include "http_test_util.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/ray_batch.h"

namespace kdrt::test {
namespace {

/// One server for the tests of this file (none of them needs special flags).
class HttpApi : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess({.cache_dir = dir_->path() / "cache"});
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
    }
    static TempDir* dir_;
    static ServerProcess* server_;
};
TempDir* HttpApi::dir_ = nullptr;
ServerProcess* HttpApi::server_ = nullptr;

TEST_F(HttpApi, UploadInEveryFormatGivesTheSameId) {
    ASSERT_TRUE(server_->running());
    auto cli = server_->client();
    const Mesh bunny = load_bunny();
    const std::string expected_id = proto::mesh_id(bunny);
    struct Case {
        const char* name;
        std::string body;
        std::string content_type;
        std::string query;
    };
    const std::vector<Case> cases = {
        {"raw", mesh_body(bunny, proto::MeshFormat::kRaw), "application/x-kdrt-mesh", ""},
        {"obj", mesh_body(bunny, proto::MeshFormat::kObj), "model/obj", ""},
        {"ply binary", mesh_body(bunny, proto::MeshFormat::kPly), "application/ply", ""},
        {"ply ascii", mesh_body(bunny, proto::MeshFormat::kPly, false), "application/ply", ""},
        {"off", mesh_body(bunny, proto::MeshFormat::kOff), "application/x-off; charset=utf-8", ""},
        {"stl binary", mesh_body(bunny, proto::MeshFormat::kStl), "model/stl", ""},
        {"stl ascii, ?format", mesh_body(bunny, proto::MeshFormat::kStl, false),
         "application/octet-stream", "?format=stl"},
    };
    bool first = true;
    for (const Case& c : cases) {
        SCOPED_TRACE(c.name);
        auto res = cli->Post("/v1/meshes" + c.query, c.body, c.content_type);
        ASSERT_TRUE(res);
        EXPECT_EQ(res->status, first ? 201 : 200) << res->body;
        auto summary = proto::decode_mesh_summary(res->body);
        ASSERT_TRUE(summary) << summary.error();
        EXPECT_EQ(summary->id, expected_id);
        EXPECT_EQ(summary->triangles, bunny.triangle_count());
        EXPECT_EQ(summary->bounds, mesh_bounds(bunny));
        EXPECT_GT(summary->tree.nodes, 0u);
        EXPECT_GT(summary->tree.build_ms, 0.0);
        EXPECT_EQ(res->get_header_value("Location"), "/v1/meshes/" + expected_id);
        first = false;
    }
    // Only the first upload built a tree; the rest were recognised by their content hash.
    EXPECT_EQ(server_->metric("kdrt_uploads_deduplicated_total"), cases.size() - 1.0);
}

TEST_F(HttpApi, ListGetAndDeleteMeshes) {
    auto cli = server_->client();
    const Mesh a = small_mesh(101), b = small_mesh(102);
    const std::string id_a = upload_id(*cli, a), id_b = upload_id(*cli, b);

    auto list = cli->Get("/v1/meshes");
    ASSERT_TRUE(list);
    ASSERT_EQ(list->status, 200);
    auto meshes = proto::decode_mesh_list(list->body);
    ASSERT_TRUE(meshes) << meshes.error();
    int found = 0;
    for (const auto& m : *meshes) found += (m.id == id_a) + (m.id == id_b);
    EXPECT_EQ(found, 2);

    auto one = cli->Get("/v1/meshes/" + id_a);
    ASSERT_TRUE(one);
    ASSERT_EQ(one->status, 200);
    auto summary = proto::decode_mesh_summary(one->body);
    ASSERT_TRUE(summary);
    EXPECT_EQ(summary->id, id_a);
    EXPECT_EQ(summary->triangles, 500u);
    EXPECT_EQ(summary->vertices, 1500u);
    EXPECT_TRUE(summary->in_memory.value_or(false));

    auto del = cli->Delete("/v1/meshes/" + id_a);
    ASSERT_TRUE(del);
    EXPECT_EQ(del->status, 204);
    EXPECT_TRUE(del->body.empty());
    expect_problem(cli->Get("/v1/meshes/" + id_a), 404);
    expect_problem(cli->Delete("/v1/meshes/" + id_a), 404);
    EXPECT_EQ(cli->Get("/v1/meshes/" + id_b)->status, 200);
    // Deleted means gone from disk too: uploading it again builds it again.
    auto again = upload(*cli, a);
    ASSERT_TRUE(again);
    EXPECT_EQ(again->status, 201);
}

TEST_F(HttpApi, BinaryIntersectMatchesTheEngineBitForBit) {
    auto cli = server_->client();
    const Mesh bunny = load_bunny();
    const std::string id = upload_id(*cli, bunny);
    const KdTree tree = build_kdtree(bunny);
    const std::vector<Ray> rays = random_rays(mesh_bounds(bunny), 20000, test_seed());
    SCOPED_TRACE(testing::Message() << "seed=" << test_seed());

    std::vector<Hit> want(rays.size());
    intersect(tree, rays, want);
    auto res =
        cli->Post("/v1/meshes/" + id + "/intersect",
                  bytes_to_string(proto::encode_rays(rays, false)), "application/x-kdrt-rays");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("Content-Type"), "application/x-kdrt-hits");
    EXPECT_EQ(res->body, bytes_to_string(proto::encode_hits(want)));
    size_t hit_count = 0;
    for (const Hit& h : want) hit_count += h.is_hit();
    EXPECT_GT(hit_count, rays.size() / 10);
    EXPECT_LT(hit_count, rays.size());

    std::vector<uint8_t> occluded_want(rays.size());
    occluded(tree, rays, occluded_want);
    auto occ =
        cli->Post("/v1/meshes/" + id + "/intersect",
                  bytes_to_string(proto::encode_rays(rays, true)), "application/x-kdrt-rays");
    ASSERT_TRUE(occ);
    ASSERT_EQ(occ->status, 200) << occ->body;
    EXPECT_EQ(occ->get_header_value("Content-Type"), "application/x-kdrt-occlusion");
    EXPECT_EQ(occ->body, bytes_to_string(proto::encode_occlusion(occluded_want)));

    // Small batches take the inline path; they must agree too.
    const std::vector<Ray> one(rays.begin(), rays.begin() + 1);
    auto single =
        cli->Post("/v1/meshes/" + id + "/intersect",
                  bytes_to_string(proto::encode_rays(one, false)), "application/x-kdrt-rays");
    ASSERT_TRUE(single);
    EXPECT_EQ(single->body, bytes_to_string(proto::encode_hits(std::span(want).first(1))));
    // A count-0 batch is valid.
    auto empty =
        cli->Post("/v1/meshes/" + id + "/intersect", bytes_to_string(proto::encode_rays({}, false)),
                  "application/x-kdrt-rays");
    ASSERT_TRUE(empty);
    EXPECT_EQ(empty->status, 200);
    EXPECT_EQ(empty->body, bytes_to_string(proto::encode_hits({})));
}

TEST_F(HttpApi, JsonIntersectMatchesTheEngine) {
    auto cli = server_->client();
    const Mesh mesh = small_mesh(7, 3000);
    const std::string id = upload_id(*cli, mesh);
    const KdTree tree = build_kdtree(mesh);
    std::vector<Ray> rays = random_rays(mesh_bounds(mesh), 2000, test_seed() + 1);
    rays[3].tmin = 0.25f;
    rays[3].tmax = 0.75f;
    std::vector<Hit> want(rays.size());
    intersect(tree, rays, want);

    auto res = cli->Post("/v1/meshes/" + id + "/intersect", proto::encode_json_rays(rays, false),
                         "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("Content-Type"), "application/json");
    auto hits = proto::decode_json_hits(res->body);
    ASSERT_TRUE(hits) << hits.error();
    ASSERT_EQ(hits->size(), want.size());
    for (size_t i = 0; i < want.size(); ++i) {
        SCOPED_TRACE(i);
        EXPECT_EQ((*hits)[i].prim, want[i].prim);
        if (want[i].is_hit()) {
            EXPECT_EQ((*hits)[i].t, want[i].t);
            EXPECT_EQ((*hits)[i].u, want[i].u);
            EXPECT_EQ((*hits)[i].v, want[i].v);
        }
    }

    // The 6-number form and the occlusion flag, written by hand.
    const Ray& r = rays[0];
    const std::string body = "{\"rays\": [[" + std::to_string(r.ox) + "," + std::to_string(r.oy) +
                             "," + std::to_string(r.oz) +
                             ",0,0,1], [0,0,-100,0,0,-1]], \"occlusion\": true}";
    auto occ = cli->Post("/v1/meshes/" + id + "/intersect", body, "application/json");
    ASSERT_TRUE(occ);
    ASSERT_EQ(occ->status, 200) << occ->body;
    auto flags = proto::decode_json_occlusion(occ->body);
    ASSERT_TRUE(flags) << flags.error();
    ASSERT_EQ(flags->size(), 2u);
    EXPECT_EQ((*flags)[1], 0);  // pointing away from everything
}

TEST_F(HttpApi, ChunkedAndSpooledUploadsWork) {
    auto cli = server_->client();
    const Mesh mesh = small_mesh(55, 2000);
    const std::string body = mesh_body(mesh, proto::MeshFormat::kObj);
    // Chunked transfer encoding: no Content-Length, the body arrives in pieces.
    size_t sent = 0;
    auto res = cli->Post(
        "/v1/meshes",
        [&](size_t, httplib::DataSink& sink) {
            const size_t n = std::min<size_t>(7777, body.size() - sent);
            sink.write(body.data() + sent, n);
            sent += n;
            if (sent == body.size()) sink.done();
            return true;
        },
        "model/obj");
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 201) << res->body;
    auto summary = proto::decode_mesh_summary(res->body);
    ASSERT_TRUE(summary);
    EXPECT_EQ(summary->id, proto::mesh_id(mesh));
}

}  // namespace
}  // namespace kdrt::test
