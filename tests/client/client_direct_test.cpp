// The client's direct ray-batch transport (client/src/http_direct.cpp, used for plain http):
// answers framed every way HTTP/1.1 allows (Content-Length, chunked, Connection: close),
// keep-alive connections the server closed while idle, oversized answers, and the bearer token.
// A fake server answers each ray with a record made of the ray's own fields, so every answer is
// checked value for value without an engine.

#include <gtest/gtest.h>

#include <bit>
#include <mutex>
#include <set>
#include <thread>

#include "client_test_util.h"
#include "fake_server.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/ray_batch.h"

namespace kdrt::test {
namespace {

/// The fake's answer to a ray: its fields, so a misplaced or mangled record shows.
Hit echo(const Ray& r) {
    return Hit{.t = r.ox, .prim = std::bit_cast<uint32_t>(r.oy), .u = r.oz, .v = r.dx};
}

std::vector<Ray> numbered_rays(size_t count) {
    std::vector<Ray> rays(count);
    for (size_t i = 0; i < count; ++i) {
        const auto f = static_cast<float>(i);
        rays[i] = Ray{
            .ox = f, .oy = f + 0.5f, .oz = -f, .tmin = 0, .dx = 1, .dy = 0, .dz = 0, .tmax = 1e30f};
    }
    return rays;
}

std::vector<Hit> echoed(const std::vector<Ray>& rays) {
    std::vector<Hit> hits;
    hits.reserve(rays.size());
    for (const Ray& r : rays) hits.push_back(echo(r));
    return hits;
}

/// The KDRH answer of a request's KDRR body (empty when the body does not decode).
std::string echo_answer(const httplib::Request& req) {
    auto batch = proto::decode_rays(std::as_bytes(std::span(req.body.data(), req.body.size())));
    if (!batch) return {};
    std::vector<Hit> hits;
    for (const Ray& r : batch->rays) hits.push_back(echo(r));
    const std::vector<std::byte> body = proto::encode_hits(hits);
    return {reinterpret_cast<const char*>(body.data()), body.size()};
}

constexpr const char* kRoute = "/v1/meshes/([^/]+)/intersect";

TEST(ClientDirect, ContentLengthAnswersArriveInOrder) {
    FakeServer fake([&](httplib::Server& http) {
        http.set_keep_alive_max_count(1000);
        http.Post(kRoute, [&](const httplib::Request& req, httplib::Response& res) {
            res.set_content(echo_answer(req), std::string(proto::kHitsMediaType));
        });
    });
    ClientOptions options = fast_options();
    options.chunk_rays = 1000;
    options.connections = 3;
    const std::vector<Ray> rays = numbered_rays(25'123);
    auto hits = Client(fake.url(), options).intersect("m", rays);
    ASSERT_TRUE(hits) << hits.error().to_string();
    EXPECT_TRUE(same_bits(*hits, echoed(rays)));
}

TEST(ClientDirect, ChunkedAnswersAreDecoded) {
    FakeServer fake([&](httplib::Server& http) {
        http.Post(kRoute, [&](const httplib::Request& req, httplib::Response& res) {
            auto body = std::make_shared<std::string>(echo_answer(req));
            // Odd piece sizes, so chunk boundaries fall inside records and headers.
            res.set_chunked_content_provider(
                std::string(proto::kHitsMediaType),
                [body, offset = size_t{0}](size_t, httplib::DataSink& sink) mutable {
                    if (offset < body->size()) {
                        const size_t n = std::min<size_t>(777, body->size() - offset);
                        sink.write(body->data() + offset, n);
                        offset += n;
                    } else {
                        sink.done();
                    }
                    return true;
                });
        });
    });
    ClientOptions options = fast_options();
    options.chunk_rays = 600;
    options.connections = 2;
    const std::vector<Ray> rays = numbered_rays(3000);
    Client client(fake.url(), options);
    for (int round = 0; round < 2; ++round) {  // the second round reuses the connections
        auto hits = client.intersect("m", rays);
        ASSERT_TRUE(hits) << hits.error().to_string();
        EXPECT_TRUE(same_bits(*hits, echoed(rays)));
    }
}

TEST(ClientDirect, ConnectionCloseAnswersGetANewConnection) {
    std::mutex mutex;
    std::set<int> ports;
    int requests = 0;
    FakeServer fake([&](httplib::Server& http) {
        http.set_keep_alive_max_count(1);  // every answer says Connection: close
        http.Post(kRoute, [&](const httplib::Request& req, httplib::Response& res) {
            {
                std::lock_guard lock(mutex);
                ports.insert(req.remote_port);
                ++requests;
            }
            res.set_content(echo_answer(req), std::string(proto::kHitsMediaType));
        });
    });
    ClientOptions options = fast_options();
    options.chunk_rays = 100;
    options.connections = 2;
    const std::vector<Ray> rays = numbered_rays(1000);
    auto hits = Client(fake.url(), options).intersect("m", rays);
    ASSERT_TRUE(hits) << hits.error().to_string();
    EXPECT_TRUE(same_bits(*hits, echoed(rays)));
    EXPECT_EQ(requests, 10);       // no request failed and was resent
    EXPECT_EQ(ports.size(), 10u);  // one connection per answer
}

TEST(ClientDirect, IdleConnectionsTheServerClosedAreReopened) {
    std::mutex mutex;
    std::set<int> ports;
    int requests = 0;
    FakeServer fake([&](httplib::Server& http) {
        http.set_keep_alive_max_count(1000);
        http.set_keep_alive_timeout(1);  // closes a connection idle for 1 s
        http.Post(kRoute, [&](const httplib::Request& req, httplib::Response& res) {
            {
                std::lock_guard lock(mutex);
                ports.insert(req.remote_port);
                ++requests;
            }
            res.set_content(echo_answer(req), std::string(proto::kHitsMediaType));
        });
    });
    ClientOptions options = fast_options();
    options.connections = 1;
    options.max_retries = 0;  // a stale connection must not cost an attempt
    Client client(fake.url(), options);
    const std::vector<Ray> rays = numbered_rays(50);
    ASSERT_TRUE(client.intersect("m", rays));
    std::this_thread::sleep_for(std::chrono::milliseconds(2500));
    auto hits = client.intersect("m", rays);
    ASSERT_TRUE(hits) << hits.error().to_string();
    EXPECT_TRUE(same_bits(*hits, echoed(rays)));
    EXPECT_EQ(requests, 2);
    EXPECT_EQ(ports.size(), 2u);
}

TEST(ClientDirect, AnAnswerLargerThanTheBatchsIsRefusedUnread) {
    FakeServer fake([&](httplib::Server& http) {
        http.Post(kRoute, [&](const httplib::Request&, httplib::Response& res) {
            const std::vector<std::byte> body = proto::encode_hits(std::vector<Hit>(200'000));
            res.set_content(reinterpret_cast<const char*>(body.data()), body.size(),
                            std::string(proto::kHitsMediaType));
        });
    });
    auto hits = Client(fake.url(), fast_options()).intersect("m", numbered_rays(10));
    ASSERT_FALSE(hits);
    EXPECT_EQ(hits.error().kind, ErrorKind::kProtocol);
    EXPECT_NE(hits.error().detail.find("Content-Length 3200016 is larger than"), std::string::npos)
        << hits.error().detail;
}

TEST(ClientDirect, TheTokenAndHostAreSentWithBatches) {
    std::mutex mutex;
    std::set<std::string> authorizations, hosts;
    FakeServer fake([&](httplib::Server& http) {
        http.Post(kRoute, [&](const httplib::Request& req, httplib::Response& res) {
            {
                std::lock_guard lock(mutex);
                authorizations.insert(req.get_header_value("Authorization"));
                hosts.insert(req.get_header_value("Host"));
            }
            res.set_content(echo_answer(req), std::string(proto::kHitsMediaType));
        });
    });
    ClientOptions options = fast_options();
    options.token = "s3cret";
    options.chunk_rays = 10;
    const std::vector<Ray> rays = numbered_rays(35);
    auto hits = Client(fake.url(), options).intersect("m", rays);
    ASSERT_TRUE(hits) << hits.error().to_string();
    EXPECT_TRUE(same_bits(*hits, echoed(rays)));
    EXPECT_EQ(authorizations, std::set<std::string>{"Bearer s3cret"});
    EXPECT_EQ(hosts, std::set<std::string>{"127.0.0.1:" + std::to_string(fake.port())});
}

TEST(ClientDirect, ImagesArriveWholeAndRenderWantsA200) {
    // 5 MB of bytes that differ from position to position, as a render's and a result's answer.
    std::string image(5'000'003, '\0');
    for (size_t i = 0; i < image.size(); ++i) image[i] = static_cast<char>((i * 131) >> 3);
    std::atomic<int> status{200};
    FakeServer fake([&](httplib::Server& http) {
        http.Post("/v1/render", [&](const httplib::Request& req, httplib::Response& res) {
            res.status = status.load();
            res.set_content(req.body.find("\"mesh\"") != std::string::npos ? image : "?",
                            "image/png");
        });
        http.Get("/v1/jobs/([^/]+)/result", [&](const httplib::Request&, httplib::Response& res) {
            res.set_content(image, "image/png");
        });
    });
    Client client(fake.url(), fast_options());
    RenderRequest request;
    request.mesh = "m";
    Job job;
    job.id = "j";
    const auto expected = std::as_bytes(std::span(image));
    auto rendered = client.render(request);
    ASSERT_TRUE(rendered) << rendered.error().to_string();
    EXPECT_TRUE(std::equal(rendered->begin(), rendered->end(), expected.begin(), expected.end()));
    auto result = client.result(job);
    ASSERT_TRUE(result) << result.error().to_string();
    EXPECT_TRUE(std::equal(result->begin(), result->end(), expected.begin(), expected.end()));

    status = 202;  // a queued job is not the image the synchronous call asked for
    auto queued = client.render(request);
    ASSERT_FALSE(queued);
    EXPECT_EQ(queued.error().kind, ErrorKind::kProtocol);
    EXPECT_NE(queued.error().detail.find("status 202 instead of 200"), std::string::npos)
        << queued.error().detail;
}

}  // namespace
}  // namespace kdrt::test
