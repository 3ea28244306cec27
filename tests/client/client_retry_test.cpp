// Transport behaviour of kdrt::Client: retries on injected 503s (Retry-After honoured) and on
// connection errors, none on 4xx, the resend policy of non-idempotent requests, chunks answered
// out of order, keep-alive connections, and answers the API does not allow.

#include <gtest/gtest.h>

#include <set>
#include <thread>

#include "client_test_util.h"
#include "fake_server.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/problem.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/trace.h"

namespace kdrt::test {
namespace {

using Clock = std::chrono::steady_clock;

double seconds_since(Clock::time_point start) {
    return std::chrono::duration<double>(Clock::now() - start).count();
}

class ClientRetry : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess({.cache_dir = dir_->path() / "cache"});
        Rng rng(test_seed() + 1);
        mesh_ = new Mesh(random_soup(rng, 1000));
        tree_ = new KdTree(build_kdtree(*mesh_));
        auto info = Client(server_url(*server_), fast_options()).upload(*mesh_);
        id_ = info ? info->id : std::string();
        ASSERT_TRUE(info) << info.error().to_string();
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete mesh_;
        delete tree_;
    }
    static std::vector<Ray> rays(size_t count, uint64_t seed) {
        Rng rng(seed);
        return oracle_rays(rng, *mesh_, *tree_, count);
    }
    static std::vector<Hit> engine_hits(const std::vector<Ray>& r) {
        std::vector<Hit> hits(r.size());
        intersect(*tree_, r, hits);
        return hits;
    }

    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* mesh_;
    static KdTree* tree_;
    static std::string id_;
};
TempDir* ClientRetry::dir_ = nullptr;
ServerProcess* ClientRetry::server_ = nullptr;
Mesh* ClientRetry::mesh_ = nullptr;
KdTree* ClientRetry::tree_ = nullptr;
std::string ClientRetry::id_;

TEST_F(ClientRetry, Injected503sAreRetriedHonouringRetryAfter) {
    FaultyProxy proxy(server_->port(), /*unavailable_first=*/2, /*retry_after_s=*/1);
    ClientOptions options = fast_options();  // 1 ms backoff: only Retry-After can make it wait
    const auto start = Clock::now();
    auto info = Client(proxy.url(), options).mesh(id_);
    const double seconds = seconds_since(start);
    ASSERT_TRUE(info) << info.error().to_string();
    EXPECT_EQ(info->id, id_);
    EXPECT_EQ(proxy.requests(), 3);
    EXPECT_GE(seconds, 1.9);  // two Retry-After: 1
    EXPECT_LT(seconds, 20.0);
    const auto log = proxy.log();
    ASSERT_EQ(log.size(), 3u);
    EXPECT_EQ(log[0], "GET /v1/meshes/" + id_ + " -> 503");
    EXPECT_EQ(log[2], "GET /v1/meshes/" + id_ + " -> 200");
}

TEST_F(ClientRetry, GatewayErrorsAreRetriedOnlyWhenIdempotent) {
    for (const int status : {502, 504}) {
        FaultyProxy proxy(server_->port(), /*unavailable_first=*/2, /*retry_after_s=*/-1, status);
        Client c(proxy.url(), fast_options());
        const auto r = rays(300, 41);
        auto hits = c.intersect(id_, r);  // a replica behind a proxy died twice: resent
        ASSERT_TRUE(hits) << hits.error().to_string();
        EXPECT_TRUE(same_bits(*hits, engine_hits(r)));
        EXPECT_EQ(proxy.requests(), 3);
    }
    FaultyProxy proxy(server_->port(), /*unavailable_first=*/1, /*retry_after_s=*/-1, 502);
    auto job = Client(proxy.url(), fast_options()).submit(small_render(id_));
    ASSERT_FALSE(job);  // the job may have been queued before the replica died: not resent
    EXPECT_EQ(job.error().status, 502);
    EXPECT_EQ(job.error().attempts, 1u);
    EXPECT_EQ(proxy.requests(), 1);
}

TEST_F(ClientRetry, Injected503sOnChunksStillGiveTheEngineAnswers) {
    FaultyProxy proxy(server_->port(), /*unavailable_first=*/2, /*retry_after_s=*/0);
    ClientOptions options = fast_options();
    options.chunk_rays = 1000;
    options.connections = 2;
    const std::vector<Ray> r = rays(5500, test_seed() + 2);
    auto hits = Client(proxy.url(), options).intersect(id_, r);
    ASSERT_TRUE(hits) << hits.error().to_string();
    EXPECT_TRUE(same_bits(*hits, engine_hits(r)));
    EXPECT_EQ(proxy.requests(), 6 + 2);  // six chunks, plus the two attempts refused with 503
}

TEST_F(ClientRetry, UploadsAreRetriedOn503) {
    FaultyProxy proxy(server_->port(), 2, 0);
    auto info = Client(proxy.url(), fast_options()).upload(data_path("diplodocus.off"));
    ASSERT_TRUE(info) << info.error().to_string();
    EXPECT_EQ(info->triangles, load_mesh(data_path("diplodocus.off")).triangle_count());
    EXPECT_EQ(proxy.requests(), 3);
}

TEST_F(ClientRetry, GivesUpAfterMaxRetriesWithTheLast503) {
    FaultyProxy proxy(server_->port(), 1000, 0);
    ClientOptions options = fast_options();
    options.max_retries = 3;
    auto info = Client(proxy.url(), options).meshes();
    ASSERT_FALSE(info);
    EXPECT_EQ(info.error().kind, ErrorKind::kServer);
    EXPECT_EQ(info.error().status, 503);
    EXPECT_EQ(info.error().title, "Over capacity");
    EXPECT_EQ(info.error().detail, "injected 503 number 4");
    EXPECT_EQ(info.error().retry_after, 0u);
    EXPECT_EQ(info.error().attempts, 4u);
    EXPECT_EQ(proxy.requests(), 4);
}

TEST_F(ClientRetry, BackoffDoublesWithoutRetryAfter) {
    FaultyProxy proxy(server_->port(), 1000, /*no Retry-After*/ -1);
    ClientOptions options = fast_options();
    options.max_retries = 3;
    options.backoff_initial = std::chrono::milliseconds(100);
    options.backoff_max = std::chrono::milliseconds(150);
    const auto start = Clock::now();
    auto info = Client(proxy.url(), options).meshes();
    const double seconds = seconds_since(start);
    ASSERT_FALSE(info);
    EXPECT_EQ(proxy.requests(), 4);
    EXPECT_GE(seconds, 0.1 + 0.15 + 0.15 - 0.01);  // 100 ms, then 200 ms capped at 150 twice
    EXPECT_LT(seconds, 10.0);
}

TEST_F(ClientRetry, RetryAfterIsCappedByMaxRetryAfter) {
    FaultyProxy proxy(server_->port(), 1, /*retry_after_s=*/3600);
    ClientOptions options = fast_options();
    options.max_retry_after = std::chrono::milliseconds(50);
    const auto start = Clock::now();
    EXPECT_TRUE(Client(proxy.url(), options).meshes());
    EXPECT_LT(seconds_since(start), 10.0);
    EXPECT_EQ(proxy.requests(), 2);
}

TEST_F(ClientRetry, ClientErrorsAreNeverRetried) {
    FaultyProxy proxy(server_->port(), 0);
    Client c(proxy.url(), fast_options());
    const std::string unknown(64, 'b');
    auto missing = c.mesh(unknown);
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().status, 404);
    EXPECT_EQ(missing.error().attempts, 1u);
    EXPECT_EQ(proxy.requests(), 1);

    std::vector<Ray> nan_rays(3);
    nan_rays[1].ox = NAN;
    auto bad_batch = c.intersect(id_, nan_rays);
    ASSERT_FALSE(bad_batch);
    EXPECT_EQ(bad_batch.error().status, 400);
    EXPECT_EQ(proxy.requests(), 2);

    auto bad_mesh = c.upload(std::as_bytes(std::span("f 1 2 3\n", 8)), proto::MeshFormat::kObj);
    ASSERT_FALSE(bad_mesh);
    EXPECT_EQ(bad_mesh.error().status, 422);
    EXPECT_EQ(proxy.requests(), 3);

    Job ghost;
    ghost.id = std::string(32, 'c');
    EXPECT_EQ(c.result(ghost).error().status, 404);
    EXPECT_EQ(proxy.requests(), 4);
}

TEST_F(ClientRetry, ReadyIsNotRetriedOn503) {
    std::atomic<int> calls{0};
    FakeServer fake([&](httplib::Server& http) {
        http.Get("/readyz", [&](const httplib::Request&, httplib::Response& res) {
            calls.fetch_add(1);
            proto::Problem p;
            p.kind = proto::ProblemKind::kNotReady;
            p.detail = "the mesh index is loading";
            p.retry_after = 1;
            res.status = 503;
            res.set_header("Retry-After", "1");
            res.set_content(proto::encode_problem(p), std::string(proto::kProblemMediaType));
        });
    });
    auto ready = Client(fake.url(), fast_options()).ready();
    ASSERT_FALSE(ready);
    EXPECT_EQ(ready.error().status, 503);
    EXPECT_EQ(ready.error().title, "Not ready");
    EXPECT_EQ(ready.error().detail, "the mesh index is loading");
    EXPECT_EQ(calls.load(), 1);
}

TEST_F(ClientRetry, ConnectionRefusedIsRetriedUntilTheServerIsUp) {
    const int port = unused_port();
    ClientOptions options = fast_options();
    options.max_retries = 50;  // 10 s of retries: room for a slow start on a loaded machine
    options.backoff_initial = std::chrono::milliseconds(100);
    options.backoff_max = std::chrono::milliseconds(200);
    Client c("http://127.0.0.1:" + std::to_string(port), options);
    std::atomic<int> calls{0};
    std::unique_ptr<FakeServer> late;
    std::thread starter([&] {
        std::this_thread::sleep_for(std::chrono::milliseconds(400));
        late = std::make_unique<FakeServer>(
            [&](httplib::Server& http) {
                http.Get("/healthz", [&](const httplib::Request&, httplib::Response& res) {
                    calls.fetch_add(1);
                    res.set_content("{\"status\":\"ok\"}", "application/json");
                });
            },
            port);
    });
    const auto start = Clock::now();
    auto healthy = c.health();
    starter.join();
    EXPECT_TRUE(healthy) << healthy.error().to_string();
    EXPECT_GE(seconds_since(start), 0.3);
    EXPECT_EQ(calls.load(), 1);
}

TEST_F(ClientRetry, DroppedConnectionsAreResentOnlyWhenIdempotent) {
    DropServer drop;
    ClientOptions options = fast_options();
    options.max_retries = 2;
    Client c(drop.url(), options);
    auto healthy = c.health();
    ASSERT_FALSE(healthy);
    EXPECT_EQ(healthy.error().kind, ErrorKind::kConnection);
    EXPECT_EQ(healthy.error().title, "connection failed");
    EXPECT_EQ(healthy.error().attempts, 3u);
    EXPECT_EQ(drop.connections(), 3);

    auto job = c.submit(small_render(id_));  // might queue a job twice: sent once
    ASSERT_FALSE(job);
    EXPECT_EQ(job.error().kind, ErrorKind::kConnection);
    EXPECT_EQ(job.error().attempts, 1u);
    EXPECT_EQ(drop.connections(), 4);
}

/// A fake intersect route that answers with the engine, later chunks first, and records which
/// connections it was asked on and how many requests ran at once.
struct OutOfOrderIntersect {
    explicit OutOfOrderIntersect(const KdTree& served, int chunk_count)
        : tree(served), chunks(chunk_count) {}

    void handle(const httplib::Request& req, httplib::Response& res) {
        const int index = arrived.fetch_add(1);
        const int now = in_flight.fetch_add(1) + 1;
        for (int seen = max_in_flight.load();
             now > seen && !max_in_flight.compare_exchange_weak(seen, now);) {
        }
        {
            std::lock_guard lock(mutex);
            ports.insert(req.remote_port);
        }
        // Early chunks wait longest, so answers complete out of order.
        std::this_thread::sleep_for(std::chrono::milliseconds(20 * std::max(0, chunks - index)));
        auto batch = proto::decode_rays(std::as_bytes(std::span(req.body.data(), req.body.size())));
        in_flight.fetch_sub(1);
        if (!batch) {
            res.status = 400;
            return;
        }
        std::vector<Hit> hits(batch->rays.size());
        intersect(tree, batch->rays, hits);
        const std::vector<std::byte> body = proto::encode_hits(hits);
        res.set_content(reinterpret_cast<const char*>(body.data()), body.size(),
                        std::string(proto::kHitsMediaType));
    }

    const KdTree& tree;
    const int chunks;
    std::atomic<int> arrived{0}, in_flight{0}, max_in_flight{0};
    std::mutex mutex;
    std::set<int> ports;
};

TEST_F(ClientRetry, ChunksAnsweredOutOfOrderAreReassembledInOrder) {
    constexpr int kChunks = 12;
    OutOfOrderIntersect route(*tree_, kChunks);
    FakeServer fake([&](httplib::Server& http) {
        http.set_keep_alive_max_count(
            1000);  // httplib's default (5) would close connections under the test
        http.Post(
            "/v1/meshes/([^/]+)/intersect",
            [&](const httplib::Request& req, httplib::Response& res) { route.handle(req, res); });
    });
    ClientOptions options = fast_options();
    options.chunk_rays = 500;
    options.connections = 3;
    const std::vector<Ray> r = rays(500 * (kChunks - 1) + 123, test_seed() + 3);
    Client c(fake.url(), options);
    auto hits = c.intersect(id_, r);
    ASSERT_TRUE(hits) << hits.error().to_string();
    EXPECT_TRUE(same_bits(*hits, engine_hits(r)));
    EXPECT_EQ(route.arrived.load(), kChunks);
    EXPECT_GE(route.max_in_flight.load(), 2);
    EXPECT_LE(route.max_in_flight.load(), 3);
    EXPECT_LE(route.ports.size(), 3u);  // keep-alive: one connection per parallel stream

    // A second call reuses the pooled connections.
    auto again = c.intersect(id_, r);
    ASSERT_TRUE(again) << again.error().to_string();
    EXPECT_TRUE(same_bits(*again, *hits));
    EXPECT_LE(route.ports.size(), 3u);
}

TEST_F(ClientRetry, AChunkErrorStopsTheBatch) {
    std::atomic<int> calls{0};
    FakeServer fake([&](httplib::Server& http) {
        http.Post("/v1/meshes/([^/]+)/intersect", [&](const httplib::Request& req,
                                                      httplib::Response& res) {
            if (calls.fetch_add(1) == 2) {
                proto::Problem p;
                p.kind = proto::ProblemKind::kBadRayBatch;
                p.detail = "malformed KDRR batch: chunk three";
                p.code = "bad_magic";
                res.status = 400;
                res.set_content(proto::encode_problem(p), std::string(proto::kProblemMediaType));
                return;
            }
            auto batch =
                proto::decode_rays(std::as_bytes(std::span(req.body.data(), req.body.size())));
            const std::vector<std::byte> body =
                proto::encode_occlusion(std::vector<uint8_t>(batch->rays.size(), 1));
            res.set_content(reinterpret_cast<const char*>(body.data()), body.size(),
                            std::string(proto::kOcclusionMediaType));
        });
    });
    ClientOptions options = fast_options();
    options.chunk_rays = 10;
    options.connections = 1;
    auto occ = Client(fake.url(), options).occluded(id_, std::vector<Ray>(1000));
    ASSERT_FALSE(occ);
    EXPECT_EQ(occ.error().status, 400);
    EXPECT_EQ(occ.error().code, "bad_magic");
    EXPECT_EQ(occ.error().detail, "malformed KDRR batch: chunk three");
    EXPECT_EQ(calls.load(), 3);  // nothing sent after the failing chunk
}

TEST_F(ClientRetry, AnswersTheApiDoesNotAllowAreProtocolErrors) {
    FakeServer fake([&](httplib::Server& http) {
        http.Post("/v1/meshes/([^/]+)/intersect",
                  [&](const httplib::Request& req, httplib::Response& res) {
                      if (req.path.find("garbage") != std::string::npos) {
                          res.set_content("not KDRH", std::string(proto::kHitsMediaType));
                          return;
                      }
                      const std::vector<std::byte> body =
                          proto::encode_hits(std::vector<Hit>(2));  // always 2 answers
                      res.set_content(reinterpret_cast<const char*>(body.data()), body.size(),
                                      std::string(proto::kHitsMediaType));
                  });
        http.Get("/v1/meshes", [](const httplib::Request&, httplib::Response& res) {
            res.set_content("{\"meshes\": 7}", "application/json");
        });
        http.Get("/v1/meshes/(.+)", [](const httplib::Request&, httplib::Response& res) {
            res.status = 502;
            res.set_content("<html>bad gateway\nfrom a proxy</html>", "text/html");
        });
        http.Post("/v1/render", [](const httplib::Request&, httplib::Response& res) {
            res.set_content("PNG", "image/png");  // ignores Prefer: respond-async
        });
    });
    Client c(fake.url(), fast_options());
    auto garbage = c.intersect("garbage", std::vector<Ray>(2));
    ASSERT_FALSE(garbage);
    EXPECT_EQ(garbage.error().kind, ErrorKind::kProtocol);
    EXPECT_EQ(garbage.error().title, "bad response");
    EXPECT_NE(garbage.error().detail.find("too_short"), std::string::npos)
        << garbage.error().detail;
    auto wrong_count = c.intersect(id_, std::vector<Ray>(1));
    ASSERT_FALSE(wrong_count);
    EXPECT_EQ(wrong_count.error().kind, ErrorKind::kProtocol);
    EXPECT_NE(wrong_count.error().detail.find("too_many_rays"), std::string::npos)
        << wrong_count.error().detail;
    auto short_count = c.intersect(id_, std::vector<Ray>(1000));
    ASSERT_FALSE(short_count);
    EXPECT_NE(short_count.error().detail.find("2 answers for 1000 rays"), std::string::npos)
        << short_count.error().detail;
    auto list = c.meshes();
    ASSERT_FALSE(list);
    EXPECT_EQ(list.error().kind, ErrorKind::kProtocol);
    auto proxy_error = c.mesh(id_);
    ASSERT_FALSE(proxy_error);
    EXPECT_EQ(proxy_error.error().kind, ErrorKind::kServer);
    EXPECT_EQ(proxy_error.error().status, 502);
    EXPECT_EQ(proxy_error.error().title, "Bad Gateway");
    EXPECT_EQ(proxy_error.error().detail, "<html>bad gateway from a proxy</html>");
    auto not_a_job = c.submit(small_render(id_));
    ASSERT_FALSE(not_a_job);
    EXPECT_EQ(not_a_job.error().kind, ErrorKind::kProtocol);
    EXPECT_NE(not_a_job.error().detail.find("instead of 202"), std::string::npos);
}

}  // namespace
}  // namespace kdrt::test
