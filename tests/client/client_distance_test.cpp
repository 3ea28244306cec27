// Client::distance against a real kdrt-server: the answers equal the engine's (computed here),
// unsigned and signed, with a maximum distance, in chunks of every size and past the server's
// max_distance_points (the client shrinks its chunks when refused); the surface status; errors
// (an unknown mesh, a NaN point named by its index in the whole call, a bad option).

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "client_test_util.h"
#include "kdrt/distance.h"
#include "kdrt/proto/distance.h"
#include "scenes.h"

namespace kdrt::test {
namespace {

/// The server's max_distance_points in this suite: smaller than the batches sent.
constexpr uint32_t kDistanceServerMaxPoints = 700;

class ClientDistance : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess(
            {.cache_dir = dir_->path() / "cache",
             .args = {"--max-distance-points", std::to_string(kDistanceServerMaxPoints)}});
        sphere_ = new Mesh(uv_sphere({0.5f, 0.5f, 0.5f}, 0.4f, 16, 32));
        sphere_tree_ = new KdTree(build_kdtree(*sphere_));
        Rng rng(test_seed() + 13);
        soup_ = new Mesh(random_soup(rng, 400, 0.2f));
        soup_tree_ = new KdTree(build_kdtree(*soup_));
        points_ = new std::vector<Vec3>();
        for (int i = 0; i < 2500; ++i)
            points_->push_back(rng.in_box({{-0.3f, -0.3f, -0.3f}, {1.3f, 1.3f, 1.3f}}));
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete sphere_;
        delete sphere_tree_;
        delete soup_;
        delete soup_tree_;
        delete points_;
    }
    static Client client(ClientOptions options = fast_options()) {
        return Client(server_url(*server_), std::move(options));
    }
    static std::string uploaded(Client& c, const Mesh& mesh) {
        auto info = c.upload(mesh);
        EXPECT_TRUE(info) << info.error().to_string();
        return info ? info->id : std::string();
    }
    /// The engine's answer, in process.
    static std::vector<ClosestPoint> engine(const KdTree& tree, const DistanceQuery& q) {
        const SurfaceIndex index = build_surface_index(tree);
        std::vector<ClosestPoint> want(points_->size());
        closest_points(tree, index, *points_, want, {q.max_distance, q.signed_query});
        return want;
    }
    /// Records compared through their wire bytes (ClosestPoint has padding; NaN points).
    static void expect_same(const std::vector<ClosestPoint>& got,
                            const std::vector<ClosestPoint>& want, bool signed_query) {
        ASSERT_EQ(got.size(), want.size());
        EXPECT_TRUE(proto::encode_distances(got, signed_query) ==
                    proto::encode_distances(want, signed_query));
    }

    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* sphere_;
    static KdTree* sphere_tree_;
    static Mesh* soup_;
    static KdTree* soup_tree_;
    static std::vector<Vec3>* points_;
};
TempDir* ClientDistance::dir_ = nullptr;
ServerProcess* ClientDistance::server_ = nullptr;
Mesh* ClientDistance::sphere_ = nullptr;
KdTree* ClientDistance::sphere_tree_ = nullptr;
Mesh* ClientDistance::soup_ = nullptr;
KdTree* ClientDistance::soup_tree_ = nullptr;
std::vector<Vec3>* ClientDistance::points_ = nullptr;

TEST_F(ClientDistance, EqualsTheEngineOnAClosedMesh) {
    ClientOptions options = fast_options();
    options.chunk_rays = 300;  // several chunks, each within the server's limit
    Client c = client(options);
    const std::string id = uploaded(c, *sphere_);
    for (const DistanceQuery& q :
         {DistanceQuery{}, DistanceQuery{0.05f, true}, DistanceQuery{INFINITY, true}}) {
        SCOPED_TRACE(proto::distance_query_string(q));
        auto got = c.distance(id, *points_, q);
        ASSERT_TRUE(got) << got.error().to_string();
        EXPECT_EQ(got->surface, "closed");
        EXPECT_TRUE(got->closed());
        EXPECT_EQ(got->signed_query, q.signed_query);
        expect_same(got->points, engine(*sphere_tree_, q), q.signed_query);
    }
    // The sphere's centre is inside, a far corner outside, and their signed distances say so.
    auto two =
        c.distance(id, std::vector<Vec3>{{0.5f, 0.5f, 0.5f}, {2, 2, 2}}, {.signed_query = true});
    ASSERT_TRUE(two) << two.error().to_string();
    EXPECT_EQ(two->points[0].side, Side::kInside);
    EXPECT_LT(two->points[0].signed_distance(), 0.0f);
    EXPECT_EQ(two->points[1].side, Side::kOutside);
    EXPECT_GT(two->points[1].signed_distance(), 0.0f);
}

TEST_F(ClientDistance, MorePointsThanTheServerTakesAreSentInSmallerChunks) {
    // The default chunk (65536 points) is over the server's max_distance_points (700): the
    // first request is refused with 413, the client learns the limit and every later request,
    // in this call and the next, fits.
    Client c = client();
    const std::string id = uploaded(c, *sphere_);
    const DistanceQuery q{INFINITY, true};
    auto got = c.distance(id, *points_, q);
    ASSERT_TRUE(got) << got.error().to_string();
    expect_same(got->points, engine(*sphere_tree_, q), true);
    auto again = c.distance(id, *points_, q);
    ASSERT_TRUE(again) << again.error().to_string();
    expect_same(again->points, got->points, true);
}

TEST_F(ClientDistance, OpenMeshHasUnknownSidesAndSaysWhy) {
    Client c = client();
    const std::string id = uploaded(c, *soup_);
    const DistanceQuery q{INFINITY, true};
    auto got = c.distance(id, *points_, q);
    ASSERT_TRUE(got) << got.error().to_string();
    EXPECT_FALSE(got->closed());
    EXPECT_EQ(got->surface.rfind("not closed: ", 0), 0u) << got->surface;
    expect_same(got->points, engine(*soup_tree_, q), true);
    for (const ClosestPoint& p : got->points) {
        ASSERT_EQ(p.side, Side::kUnknown);
        ASSERT_TRUE(std::isnan(p.signed_distance()));
    }
}

TEST_F(ClientDistance, EmptyBatchAsksTheServer) {
    Client c = client();
    const std::string id = uploaded(c, *sphere_);
    auto got = c.distance(id, {});
    ASSERT_TRUE(got) << got.error().to_string();
    EXPECT_TRUE(got->points.empty());
    EXPECT_EQ(got->surface, "closed");
    auto unknown = c.distance(std::string(64, 'a'), {});
    ASSERT_FALSE(unknown);
    EXPECT_EQ(unknown.error().status, 404);
}

TEST_F(ClientDistance, Errors) {
    ClientOptions options = fast_options();
    options.chunk_rays = 100;
    Client c = client(options);
    const std::string id = uploaded(c, *sphere_);
    // An unknown mesh is the server's 404.
    auto unknown = c.distance(std::string(64, 'a'), *points_);
    ASSERT_FALSE(unknown);
    EXPECT_EQ(unknown.error().kind, ErrorKind::kServer);
    EXPECT_EQ(unknown.error().status, 404);
    // A NaN point is named by its index in the call (not in its chunk), before anything is sent.
    std::vector<Vec3> points = *points_;
    points[1234].y = std::numeric_limits<float>::quiet_NaN();
    auto nan = c.distance(id, points);
    ASSERT_FALSE(nan);
    EXPECT_EQ(nan.error().kind, ErrorKind::kInput);
    EXPECT_EQ(nan.error().code, "non_finite_point");
    EXPECT_NE(nan.error().detail.find("point 1234: field y is NaN"), std::string::npos)
        << nan.error().to_string();
    points[1234].y = 0.0f;
    points[7].z = -std::numeric_limits<float>::infinity();
    nan = c.distance(id, points);
    ASSERT_FALSE(nan);
    EXPECT_NE(nan.error().detail.find("point 7: field z is -inf"), std::string::npos)
        << nan.error().to_string();
    // A negative max_distance is the server's 400 naming the parameter.
    auto bad = c.distance(id, *points_, {.max_distance = -1.0f});
    ASSERT_FALSE(bad);
    EXPECT_EQ(bad.error().status, 400);
    EXPECT_NE(bad.error().detail.find("max_distance"), std::string::npos)
        << bad.error().to_string();
}

}  // namespace
}  // namespace kdrt::test
