// POST /v1/meshes/{id}/distance against the real binary: KDRD answers equal the engine's (signed
// and unsigned, with a maximum distance), X-Kdrt-Surface says whether the mesh is closed, and
// every bad option or body is a problem+json naming what is wrong (the point index for NaN
// points), before any work.

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "http_test_util.h"
#include "kdrt/distance.h"
#include "kdrt/proto/distance.h"

namespace kdrt::test {
namespace {

class HttpDistance : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess(
            {.cache_dir = dir_->path() / "cache", .args = {"--max-distance-points", "5000"}});
        sphere_ = new Mesh(uv_sphere({0.5f, 0.5f, 0.5f}, 0.4f, 24, 48));
        sphere_tree_ = new KdTree(build_kdtree(*sphere_));
        sphere_id_ = upload_id(*server_->client(), *sphere_);
        Rng rng(test_seed() + 7);
        soup_ = new Mesh(random_soup(rng, 600, 0.2f));
        soup_id_ = upload_id(*server_->client(), *soup_);
        points_ = new std::vector<Vec3>();
        for (int i = 0; i < 2000; ++i)
            points_->push_back(rng.in_box({{-0.5f, -0.5f, -0.5f}, {1.5f, 1.5f, 1.5f}}));
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete sphere_;
        delete sphere_tree_;
        delete soup_;
        delete points_;
    }
    static httplib::Result post(const std::string& id, const std::string& query,
                                const std::string& body) {
        return server_->client()->Post("/v1/meshes/" + id + "/distance?" + query, body,
                                       std::string(proto::kPointMediaType));
    }
    static httplib::Result post(const std::string& query) {
        return post(sphere_id_, query, bytes_to_string(proto::encode_points(*points_)));
    }
    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* sphere_;
    static KdTree* sphere_tree_;
    static std::string sphere_id_;
    static Mesh* soup_;
    static std::string soup_id_;
    static std::vector<Vec3>* points_;
};
TempDir* HttpDistance::dir_ = nullptr;
ServerProcess* HttpDistance::server_ = nullptr;
Mesh* HttpDistance::sphere_ = nullptr;
KdTree* HttpDistance::sphere_tree_ = nullptr;
std::string HttpDistance::sphere_id_;
Mesh* HttpDistance::soup_ = nullptr;
std::string HttpDistance::soup_id_;
std::vector<Vec3>* HttpDistance::points_ = nullptr;

TEST_F(HttpDistance, AnswerIsTheEngines) {
    const SurfaceIndex index = build_surface_index(*sphere_tree_);
    ASSERT_TRUE(index.closed);
    for (const proto::DistanceQuery& q : {proto::DistanceQuery{}, proto::DistanceQuery{0.1f, true},
                                          proto::DistanceQuery{INFINITY, true}}) {
        const std::string query = proto::distance_query_string(q);
        SCOPED_TRACE(query);
        std::vector<ClosestPoint> want(points_->size());
        closest_points(*sphere_tree_, index, *points_, want, {q.max_distance, q.signed_query});
        auto res = post(query);
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 200) << res->body;
        EXPECT_EQ(res->get_header_value("Content-Type"), proto::kDistanceMediaType);
        EXPECT_EQ(res->get_header_value("X-Kdrt-Surface"), "closed");
        EXPECT_TRUE(res->body == bytes_to_string(proto::encode_distances(want, q.signed_query)));
    }
    // Inside the sphere is inside.
    auto res = post(
        sphere_id_, "signed=true",
        bytes_to_string(proto::encode_points(std::vector<Vec3>{{0.5f, 0.5f, 0.5f}, {2, 2, 2}})));
    ASSERT_TRUE(res);
    auto answer = proto::decode_distances(string_to_bytes(res->body));
    ASSERT_TRUE(answer) << answer.error().to_string();
    EXPECT_EQ(answer->points[0].side, Side::kInside);
    EXPECT_EQ(answer->points[1].side, Side::kOutside);
}

TEST_F(HttpDistance, OpenMeshHasNoSideAndSaysWhy) {
    auto res = post(soup_id_, "signed=true", bytes_to_string(proto::encode_points(*points_)));
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("X-Kdrt-Surface").rfind("not closed: ", 0), 0u);
    auto answer = proto::decode_distances(string_to_bytes(res->body));
    ASSERT_TRUE(answer);
    for (const ClosestPoint& c : answer->points) {
        ASSERT_TRUE(c.found());
        ASSERT_EQ(c.side, Side::kUnknown);
    }
}

TEST_F(HttpDistance, BadOptionsNameTheParameter) {
    for (const char* q :
         {"max_distance=-1", "max_distance=nan", "max_distance=x", "signed=maybe"}) {
        SCOPED_TRACE(q);
        const proto::Problem p = expect_problem(post(q), 400);
        const std::string name = std::string(q).substr(0, std::string(q).find('='));
        EXPECT_NE(p.detail.find(name), std::string::npos) << p.detail;
    }
}

TEST_F(HttpDistance, BadBodiesAreRefused) {
    // A NaN point is named by index and field.
    std::vector<Vec3> points(4, Vec3{0, 0, 0});
    points[3].z = std::numeric_limits<float>::quiet_NaN();
    proto::Problem p =
        expect_problem(post(sphere_id_, "", bytes_to_string(proto::encode_points(points))), 400);
    EXPECT_NE(p.detail.find("point 3: field z is NaN"), std::string::npos) << p.detail;
    EXPECT_EQ(p.code, "non_finite_point");
    points[3].z = std::numeric_limits<float>::infinity();
    p = expect_problem(post(sphere_id_, "", bytes_to_string(proto::encode_points(points))), 400);
    EXPECT_NE(p.detail.find("point 3"), std::string::npos) << p.detail;
    // A truncated body, and a KDRR batch sent as points.
    std::string body = bytes_to_string(proto::encode_points(*points_));
    body.resize(body.size() - 5);
    p = expect_problem(post(sphere_id_, "", body), 400);
    EXPECT_EQ(p.code, "length_mismatch");
    p = expect_problem(post(sphere_id_, "", "KDRR" + std::string(12, '\0')), 400);
    EXPECT_EQ(p.code, "bad_magic");
    // More points than max_distance_points (5000): refused before the body is read.
    const std::vector<Vec3> many(5001, Vec3{0, 0, 0});
    p = expect_problem(post(sphere_id_, "", bytes_to_string(proto::encode_points(many))), 413);
    EXPECT_NE(p.detail.find("max_distance_points"), std::string::npos) << p.detail;
    // Other media types, and an unknown mesh.
    expect_problem(
        server_->client()->Post("/v1/meshes/" + sphere_id_ + "/distance", "{}", "application/json"),
        415);
    expect_problem(post(std::string(64, 'a'), "", bytes_to_string(proto::encode_points(points))),
                   404);
}

/// kdrt_cache_bytes{where="memory"} of /metrics.
double cache_memory_bytes(ServerProcess& server) {
    auto res = server.client()->Get("/metrics");
    if (!res || res->status != 200) return -1;
    const std::string key = "\nkdrt_cache_bytes{where=\"memory\"} ";
    const size_t at = res->body.find(key);
    return at == std::string::npos ? -1 : std::stod(res->body.substr(at + key.size()));
}

TEST_F(HttpDistance, SurfaceIndexCountsTowardsTheMemoryBudget) {
    // A mesh no other test has asked a distance of: its first query builds its index, which
    // the cache's memory (what memory_budget bounds) then counts, 84 bytes a triangle.
    Rng rng(test_seed() + 91);
    const Mesh mesh = random_soup(rng, 2000, 0.1f);
    const std::string id = upload_id(*server_->client(), mesh);
    const double before = cache_memory_bytes(*server_);
    ASSERT_GT(before, 0);
    auto res = post(id, "", bytes_to_string(proto::encode_points(*points_)));
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    const double after = cache_memory_bytes(*server_);
    EXPECT_GE(after - before, 84.0 * 2000);
    EXPECT_LE(after - before, 84.0 * 2000 + 4096);
    // A second query reuses it.
    ASSERT_TRUE(post(id, "", bytes_to_string(proto::encode_points(*points_))));
    EXPECT_EQ(cache_memory_bytes(*server_), after);
}

TEST_F(HttpDistance, EmptyBatchIsAnEmptyAnswer) {
    auto res = post(sphere_id_, "", bytes_to_string(proto::encode_points({})));
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_TRUE(res->body == bytes_to_string(proto::encode_distances({}, false)));
}

}  // namespace
}  // namespace kdrt::test
