// A 5M-ray batch through kdrt::Client (chunked, several keep-alive connections in parallel)
// against a real kdrt-server equals the engine in process, bit for bit. KDRT_TEST_SCALE scales
// the ray count (0.05 under the sanitizers).

#include <gtest/gtest.h>

#include <cmath>

#include "client_test_util.h"
#include "kdrt/raygen.h"
#include "kdrt/trace.h"

namespace kdrt::test {
namespace {

TEST(ClientChunked, FiveMillionRaysEqualTheEngine) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    ASSERT_GT(server.port(), 0);
    const Mesh mesh = load_mesh(data_path("bunny00.off"));
    const KdTree tree = build_kdtree(mesh);
    // Camera rays of the default view: every pixel's answer differs from its neighbours', so a
    // chunk put back in the wrong place shows.
    const auto res =
        static_cast<uint32_t>(std::lround(std::sqrt(static_cast<double>(scaled(5'000'000)))));
    const std::vector<Ray> rays = generate_rays(tree, {.kind = RayKind::kPrimary, .res = res});
    SCOPED_TRACE(testing::Message() << rays.size() << " rays");

    ClientOptions options = fast_options();
    options.connections = 3;
    // At least 19 chunks at every scale, the last one short.
    options.chunk_rays = std::min<size_t>(options.chunk_rays, rays.size() / 19 + 1);
    ASSERT_NE(rays.size() % options.chunk_rays, 0u);
    Client client(server_url(server), options);
    auto info = client.upload(data_path("bunny00.off"));
    ASSERT_TRUE(info) << info.error().to_string();

    auto hits = client.intersect(info->id, rays);
    ASSERT_TRUE(hits) << hits.error().to_string();
    std::vector<Hit> want(rays.size());
    intersect(tree, rays, want);
    ASSERT_EQ(hits->size(), want.size());
    size_t first_difference = 0;
    while (first_difference < want.size() &&
           std::memcmp(&(*hits)[first_difference], &want[first_difference], sizeof(Hit)) == 0)
        ++first_difference;
    EXPECT_EQ(first_difference, want.size()) << "first different answer: ray " << first_difference;
    const auto hit_count =
        std::count_if(want.begin(), want.end(), [](const Hit& h) { return h.is_hit(); });
    EXPECT_GT(hit_count, 0);
    EXPECT_LT(static_cast<size_t>(hit_count), want.size());

    // Shadow rays from the primary hits towards a light: an occlusion batch of incoherent rays.
    const auto shadow_res =
        static_cast<uint32_t>(std::lround(std::sqrt(static_cast<double>(scaled(1'000'000)))));
    const std::vector<Ray> shadow =
        generate_rays(tree, {.kind = RayKind::kShadow, .res = shadow_res});
    auto occ = client.occluded(info->id, shadow);
    ASSERT_TRUE(occ) << occ.error().to_string();
    std::vector<uint8_t> want_occ(shadow.size());
    occluded(tree, shadow, want_occ);
    EXPECT_EQ(*occ, want_occ);
    EXPECT_GT(std::count(want_occ.begin(), want_occ.end(), uint8_t{1}), 0);
}

}  // namespace
}  // namespace kdrt::test
