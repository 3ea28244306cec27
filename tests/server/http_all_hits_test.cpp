// POST /v1/meshes/{id}/intersect_all against the real binary: KDRM answers equal the engine's in
// every layout, KDRC counts equal the engine's, and every bad option or body is a problem+json
// naming what is wrong, before any work.

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <limits>

#include "http_test_util.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/query.h"

namespace kdrt::test {
namespace {

class HttpAllHits : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess({.cache_dir = dir_->path() / "cache",
                                     .args = {"--max-hits-per-ray", "64", "--max-rays", "5000",
                                              "--batch-memory-budget", "64M"}});
        Rng rng(test_seed() + 5);
        mesh_ = new Mesh(random_soup(rng, 800, 0.3f));
        tree_ = new KdTree(build_kdtree(*mesh_));
        id_ = upload_id(*server_->client(), *mesh_);
        rays_ = new std::vector<Ray>(random_rays(mesh_bounds(*mesh_), 2000, test_seed()));
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete mesh_;
        delete tree_;
        delete rays_;
    }
    static httplib::Result post(const std::string& query, const std::string& body) {
        return server_->client()->Post("/v1/meshes/" + id_ + "/intersect_all?" + query, body,
                                       "application/x-kdrt-rays");
    }
    static httplib::Result post(const std::string& query) {
        return post(query, bytes_to_string(proto::encode_rays(*rays_, false)));
    }
    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* mesh_;
    static KdTree* tree_;
    static std::string id_;
    static std::vector<Ray>* rays_;
};
TempDir* HttpAllHits::dir_ = nullptr;
ServerProcess* HttpAllHits::server_ = nullptr;
Mesh* HttpAllHits::mesh_ = nullptr;
KdTree* HttpAllHits::tree_ = nullptr;
std::string HttpAllHits::id_;
std::vector<Ray>* HttpAllHits::rays_ = nullptr;

TEST_F(HttpAllHits, AnswerIsTheEnginesInEveryLayout) {
    for (const bool merge : {false, true}) {
        const AllHits want = intersect_all(*tree_, *rays_, AllHitsOptions{5, merge});
        std::vector<Vec3> normals(want.hits.size()), points(want.hits.size());
        hit_attributes(*tree_, want.hits, normals, points);
        for (const auto fields :
             {proto::HitFields::kFull, proto::HitFields::kT, proto::HitFields::kTPrim}) {
            for (const bool attrs : {false, true}) {
                proto::MultiHitQuery q{5, merge, false, {fields, attrs, attrs}};
                SCOPED_TRACE(proto::multi_hit_query_string(q));
                auto res = post(proto::multi_hit_query_string(q));
                ASSERT_TRUE(res);
                ASSERT_EQ(res->status, 200) << res->body;
                EXPECT_EQ(res->get_header_value("Content-Type"), proto::kMultiHitMediaType);
                proto::MultiHitsView view;
                view.layout = q.layout;
                view.merged = merge;
                view.max_hits = 5;
                view.offsets = want.offsets;
                view.counts = want.counts;
                view.hits = want.hits;
                view.normals = normals;
                view.points = points;
                EXPECT_TRUE(res->body == bytes_to_string(proto::encode_multi_hits(view)));
            }
        }
        auto res = post("count_only=true&merge_coincident=" + std::string(merge ? "1" : "0"));
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 200) << res->body;
        EXPECT_EQ(res->get_header_value("Content-Type"), proto::kHitCountMediaType);
        EXPECT_TRUE(res->body == bytes_to_string(proto::encode_hit_counts(want.counts)));
    }
}

TEST_F(HttpAllHits, NormalsAreUnitAndPointsOnTheRay) {
    auto res = post("max_hits=64&normal=true&point=true");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto answer = proto::decode_multi_hits(string_to_bytes(res->body));
    ASSERT_TRUE(answer) << answer.error().to_string();
    ASSERT_GT(answer->hits.size(), rays_->size());
    size_t bad = 0;
    for (size_t i = 0; i < rays_->size(); ++i) {
        const Ray& r = (*rays_)[i];
        for (uint64_t k = answer->offsets[i]; k < answer->offsets[i + 1]; ++k) {
            const proto::HitRecord& h = answer->hits[k];
            const float len = std::sqrt(dot(h.normal, h.normal));
            const Vec3 on_ray = Vec3{r.ox, r.oy, r.oz} + Vec3{r.dx, r.dy, r.dz} * h.t;
            const Vec3 diff = on_ray - h.point;
            bad += std::fabs(len - 1.0f) > 1e-5f || std::sqrt(dot(diff, diff)) > 1e-4f;
            if (k > answer->offsets[i]) bad += h.t < answer->hits[k - 1].t;
        }
    }
    EXPECT_EQ(bad, 0u);
}

TEST_F(HttpAllHits, BadOptionsNameTheParameter) {
    struct Case {
        std::string query;
        std::string names;
    };
    const Case cases[] = {
        {"max_hits=0", "max_hits"},
        {"max_hits=65", "max_hits"},
        {"max_hits=abc", "max_hits"},
        {"merge_coincident=maybe", "merge_coincident"},
        {"count_only=2", "count_only"},
        {"fields=uvw", "fields"},
        {"normal=yes", "normal"},
        {"point=on", "point"},
        {"invalid_rays=skip", "invalid_rays"},
    };
    for (const Case& c : cases) {
        SCOPED_TRACE(c.query);
        const proto::Problem p = expect_problem(post(c.query), 400);
        EXPECT_NE(p.detail.find(c.names), std::string::npos) << p.detail;
    }
    // The limit is named too.
    const proto::Problem p = expect_problem(post("max_hits=65"), 400);
    EXPECT_NE(p.detail.find("64"), std::string::npos) << p.detail;
}

TEST_F(HttpAllHits, BadBodiesAreRefused) {
    // A NaN ray is named by index and field (the default invalid_rays=refuse).
    std::vector<Ray> rays(3, (*rays_)[0]);
    rays[2].dy = std::numeric_limits<float>::quiet_NaN();
    proto::Problem p =
        expect_problem(post("", bytes_to_string(proto::encode_rays(rays, false))), 400);
    EXPECT_NE(p.detail.find("ray 2"), std::string::npos) << p.detail;
    EXPECT_NE(p.detail.find("dy"), std::string::npos) << p.detail;
    // With invalid_rays=miss it has no hits.
    auto res =
        post("invalid_rays=miss&count_only=true", bytes_to_string(proto::encode_rays(rays, false)));
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto counts = proto::decode_hit_counts(string_to_bytes(res->body));
    ASSERT_TRUE(counts);
    EXPECT_EQ((*counts)[2], 0u);
    // The occlusion flag belongs to /intersect.
    const std::vector<Ray> valid(2, (*rays_)[0]);
    p = expect_problem(post("", bytes_to_string(proto::encode_rays(valid, true))), 400);
    EXPECT_NE(p.detail.find("occlusion"), std::string::npos) << p.detail;
    // A truncated body.
    std::string body = bytes_to_string(proto::encode_rays(*rays_, false));
    body.resize(body.size() - 5);
    p = expect_problem(post("", body), 400);
    EXPECT_EQ(p.code, "length_mismatch");
    // More rays than max_rays (5000).
    const std::vector<Ray> many(5001, (*rays_)[0]);
    p = expect_problem(post("", bytes_to_string(proto::encode_rays(many, false))), 413);
    // JSON is not taken here.
    auto json =
        server_->client()->Post("/v1/meshes/" + id_ + "/intersect_all", "{}", "application/json");
    expect_problem(json, 415);
    // An unknown mesh.
    auto unknown = server_->client()->Post("/v1/meshes/" + std::string(64, 'a') + "/intersect_all",
                                           bytes_to_string(proto::encode_rays(rays, false)),
                                           "application/x-kdrt-rays");
    expect_problem(unknown, 404);
}

TEST_F(HttpAllHits, MemoryBudgetIsCheckedBeforeTheBody) {
    // A batch whose largest answer could never fit batch_memory_budget is 413, naming it and
    // max_hits: 2000 rays x max_hits 1024 is about 2000 x 1024 x 72 bytes, far above 1 MiB.
    TempDir dir;
    ServerProcess small({.cache_dir = dir.path() / "cache",
                         .args = {"--batch-memory-budget", "1M", "--max-hits-per-ray", "1024"}});
    const std::string id = upload_id(*small.client(), *mesh_);
    const std::vector<Ray> rays(2000, (*rays_)[0]);
    auto res = small.client()->Post("/v1/meshes/" + id + "/intersect_all?max_hits=1024",
                                    bytes_to_string(proto::encode_rays(rays, false)),
                                    "application/x-kdrt-rays");
    const proto::Problem p = expect_problem(res, 413);
    EXPECT_NE(p.detail.find("batch_memory_budget"), std::string::npos) << p.detail;
    EXPECT_NE(p.detail.find("max_hits"), std::string::npos) << p.detail;
    // The same rays with max_hits=1 fit.
    res = small.client()->Post("/v1/meshes/" + id + "/intersect_all?max_hits=1",
                               bytes_to_string(proto::encode_rays(rays, false)),
                               "application/x-kdrt-rays");
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 200) << res->body;
}

}  // namespace
}  // namespace kdrt::test
