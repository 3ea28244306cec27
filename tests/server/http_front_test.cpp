// kdrt's HTTP front (server/http/http_front.*) against a real kdrt-server, for what it does that
// cpp-httplib's server did differently: 100 Continue only once a route reads the body, request
// targets up to the head limit, chunked batches admitted as they arrive, and request bytes
// counted once. (Slow clients, 408, 431, 503 and pipelining: http_connections_test.cpp.)

#include <gtest/gtest.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <regex>
#include <string>
#include <thread>

#include "http_test_util.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/scene.h"

namespace kdrt::test {
namespace {

using namespace std::chrono_literals;

/// What arrives on `fd` within `timeout` (until the peer closes or is silent that long).
std::string receive_for(int fd, std::chrono::milliseconds timeout) {
    std::string out;
    char buf[4096];
    pollfd p{fd, POLLIN, 0};
    while (::poll(&p, 1, static_cast<int>(timeout.count())) > 0) {
        const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
        if (n <= 0) break;
        out.append(buf, static_cast<size_t>(n));
    }
    return out;
}

/// The `in=` bytes of the access-log line of the last request on `route`.
uint64_t logged_bytes_in(const std::string& log, const std::string& route) {
    const size_t at = log.rfind("route=" + route + " ");
    if (at == std::string::npos) return 0;
    const size_t in = log.find(" in=", at);
    return std::stoull(log.substr(in + 4, log.find(' ', in + 4) - in - 4));
}

/// A chunked body: `data` in chunks of `piece` bytes, then the last chunk.
std::string chunked(const std::string& data, size_t piece) {
    std::string out;
    for (size_t at = 0; at < data.size(); at += piece) {
        const std::string part = data.substr(at, piece);
        char size[32];
        std::snprintf(size, sizeof size, "%zx\r\n", part.size());
        out += size + part + "\r\n";
    }
    return out + "0\r\n\r\n";
}

/// The body of an HTTP reply.
std::string body_of(const std::string& reply) { return reply.substr(reply.find("\r\n\r\n") + 4); }

/// The answers to a POST (`head`: its request line and headers, no framing) of `body`, sent once
/// with a Content-Length and once chunked; each must be 200.
struct SizedAndChunked {
    std::string sized, chunked;
};
SizedAndChunked post_sized_and_chunked(int port, const std::string& head, const std::string& body) {
    SizedAndChunked out;
    out.sized = raw_exchange(port,
                             head + "Content-Length: " + std::to_string(body.size()) +
                                 "\r\nConnection: close\r\n\r\n" + body,
                             10s);
    out.chunked = raw_exchange(
        port, head + "Transfer-Encoding: chunked\r\nConnection: close\r\n\r\n" + chunked(body, 100),
        10s);
    EXPECT_EQ(out.sized.rfind("HTTP/1.1 200", 0), 0u) << out.sized.substr(0, 400);
    EXPECT_EQ(out.chunked.rfind("HTTP/1.1 200", 0), 0u) << out.chunked.substr(0, 400);
    return out;
}

class HttpFront : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess(
            {.cache_dir = dir_->path() / "cache",
             .args = {"--batch-memory-budget", "4M", "--max-hits-per-ray", "1024"}});
        mesh_ = new Mesh(small_mesh(11, 800));
        id_ = upload_id(*server_->client(), *mesh_);
        rays_ = new std::vector<Ray>(random_rays(mesh_bounds(*mesh_), 10, 3));
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete mesh_;
        delete rays_;
    }

    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* mesh_;
    static std::vector<Ray>* rays_;
    static std::string id_;
};
TempDir* HttpFront::dir_ = nullptr;
ServerProcess* HttpFront::server_ = nullptr;
Mesh* HttpFront::mesh_ = nullptr;
std::vector<Ray>* HttpFront::rays_ = nullptr;
std::string HttpFront::id_;

TEST_F(HttpFront, ExpectContinueIsRefusedBeforeThe100WhenTheBatchCanNeverFit) {
    // 100000 rays x max_hits 1024 need far more than the 4 MiB budget: the answer is 413 at
    // once, without inviting the 3.2 MB body first (issue 25 item 5).
    const uint64_t body = proto::kdrr_body_size(100000);
    const int fd = connect_loopback(server_->port());
    ASSERT_GE(fd, 0);
    ASSERT_TRUE(send_all(fd, "POST /v1/meshes/" + id_ +
                                 "/intersect_all?max_hits=1024 HTTP/1.1\r\nHost: x\r\n"
                                 "Content-Type: application/x-kdrt-rays\r\nContent-Length: " +
                                 std::to_string(body) + "\r\nExpect: 100-continue\r\n\r\n"));
    const std::string reply = receive_for(fd, 3s);
    ::close(fd);
    EXPECT_EQ(reply.rfind("HTTP/1.1 413", 0), 0u) << reply;
    EXPECT_EQ(reply.find("100 Continue"), std::string::npos) << reply;
    EXPECT_NE(reply.find("batch_memory_budget"), std::string::npos) << reply;
}

TEST_F(HttpFront, ExpectContinueGets100ThenTheAnswer) {
    const std::string body = bytes_to_string(proto::encode_rays(*rays_, false));
    const int fd = connect_loopback(server_->port());
    ASSERT_GE(fd, 0);
    ASSERT_TRUE(send_all(fd, "POST /v1/meshes/" + id_ +
                                 "/intersect HTTP/1.1\r\nHost: x\r\n"
                                 "Content-Type: application/x-kdrt-rays\r\nContent-Length: " +
                                 std::to_string(body.size()) + "\r\nExpect: 100-continue\r\n\r\n"));
    const std::string interim = receive_for(fd, 2s);
    EXPECT_EQ(interim, "HTTP/1.1 100 Continue\r\n\r\n");
    ASSERT_TRUE(send_all(fd, body));
    const std::string reply = receive_for(fd, 2s);
    ::close(fd);
    EXPECT_EQ(reply.rfind("HTTP/1.1 200", 0), 0u) << reply;
    EXPECT_NE(reply.find(engine_hits(*mesh_, *rays_)), std::string::npos);
}

TEST_F(HttpFront, ChunkedIntersectAllIsAdmittedAsItArrives) {
    // 10 rays with max_hits=1, chunked: no Content-Length, so the batch's memory is taken as the
    // body arrives, not for the largest batch there could be (issue 25 item 2).
    const std::string body = bytes_to_string(proto::encode_rays(*rays_, false));
    const std::string head = "POST /v1/meshes/" + id_ +
                             "/intersect_all?max_hits=1 HTTP/1.1\r\nHost: x\r\n"
                             "Content-Type: application/x-kdrt-rays\r\n";
    const SizedAndChunked answers = post_sized_and_chunked(server_->port(), head, body);
    EXPECT_EQ(body_of(answers.chunked), body_of(answers.sized));
    // A chunked batch past the budget is still refused, once it has grown past it.
    const std::vector<Ray> many(100000, (*rays_)[0]);
    const std::string big = bytes_to_string(proto::encode_rays(many, false));
    const std::string refused = raw_exchange(
        server_->port(),
        "POST /v1/meshes/" + id_ +
            "/intersect_all?max_hits=1024 HTTP/1.1\r\nHost: x\r\n"
            "Content-Type: application/x-kdrt-rays\r\nTransfer-Encoding: chunked\r\n\r\n" +
            chunked(big, 65536),
        10s);
    EXPECT_EQ(refused.rfind("HTTP/1.1 413", 0), 0u) << refused.substr(0, 400);
}

TEST_F(HttpFront, ChunkedIntersectTakesTheSharedBatchPath) {
    // /intersect reads its batch through Routes::read_batch, as intersect_all does (issue 24):
    // chunked, its memory is taken once its header says how many rays follow, not for max_rays
    // (16 + 48 x 2^24 bytes, far over this server's 4 MiB: 413 before), and its bytes are
    // counted once.
    const std::string head = "POST /v1/meshes/" + id_ +
                             "/intersect HTTP/1.1\r\nHost: x\r\n"
                             "Content-Type: application/x-kdrt-rays\r\n";
    const std::string route = "route=/v1/meshes/{id}/intersect ";
    const auto lines = [&](const std::string& log) {
        size_t n = 0;
        for (size_t at = log.find(route); at != std::string::npos; at = log.find(route, at + 1))
            ++n;
        return n;
    };
    const size_t logged_before = lines(server_->log());
    std::string body;
    for (const bool occlusion : {false, true}) {
        SCOPED_TRACE(occlusion ? "occlusion" : "closest hit");
        body = bytes_to_string(proto::encode_rays(*rays_, occlusion));
        const SizedAndChunked answers = post_sized_and_chunked(server_->port(), head, body);
        EXPECT_EQ(body_of(answers.chunked), body_of(answers.sized));
        if (!occlusion) {
            EXPECT_EQ(body_of(answers.chunked), engine_hits(*mesh_, *rays_));
        }
    }
    // The access-log line is written after the answer is sent: wait for the last one.
    std::string log = server_->log();
    for (int i = 0; i < 3000 && lines(log) < logged_before + 4; ++i) {
        std::this_thread::sleep_for(10ms);
        log = server_->log();
    }
    EXPECT_EQ(logged_bytes_in(log, "/v1/meshes/{id}/intersect"), body.size());

    // A chunked batch whose header asks for more rays than the budget could ever hold is 413
    // once the header is in, before the rest of its body.
    const std::vector<Ray> many(100000, (*rays_)[0]);
    const std::string start = bytes_to_string(proto::encode_rays(many, false)).substr(0, 4096);
    const int fd = connect_loopback(server_->port());
    ASSERT_GE(fd, 0);
    char size[32];
    std::snprintf(size, sizeof size, "%zx\r\n", start.size());
    ASSERT_TRUE(send_all(fd, head + "Transfer-Encoding: chunked\r\n\r\n" + size + start + "\r\n"));
    const std::string refused = receive_for(fd, 5s);
    ::close(fd);
    EXPECT_EQ(refused.rfind("HTTP/1.1 413", 0), 0u) << refused.substr(0, 400);
    EXPECT_NE(refused.find("more than batch_memory_budget"), std::string::npos) << refused;
    EXPECT_NE(refused.find("100000 rays"), std::string::npos) << refused;
}

TEST_F(HttpFront, RequestBytesAreCountedOnce) {
    // distance, intersect_all and scan counted their bodies twice (issue 25 item 9).
    auto cli = server_->client();
    const std::string rays = bytes_to_string(proto::encode_rays(*rays_, false));
    ASSERT_EQ(
        cli->Post("/v1/meshes/" + id_ + "/intersect_all", rays, "application/x-kdrt-rays")->status,
        200);
    const std::vector<Vec3> points = {{0, 0, 0}, {1, 2, 3}};
    const std::string kdrp = bytes_to_string(proto::encode_points(points));
    ASSERT_EQ(
        cli->Post("/v1/meshes/" + id_ + "/distance", kdrp, std::string(proto::kPointMediaType))
            ->status,
        200);
    const std::string scan =
        R"({"pinhole": {"camera": {"eye": [1, 0.5, -5], "look_at": [0, 0, 0], "fov": 50},
            "width": 8, "height": 6, "output": "range"}})";
    auto scanned = cli->Post("/v1/meshes/" + id_ + "/scan", scan, "application/json");
    ASSERT_TRUE(scanned);
    // The access-log line is written after the answer is sent: wait for the scan's (the last).
    std::string log = server_->log();
    for (int i = 0; i < 3000 && logged_bytes_in(log, "/v1/meshes/{id}/scan") == 0; ++i) {
        std::this_thread::sleep_for(10ms);
        log = server_->log();
    }
    EXPECT_EQ(logged_bytes_in(log, "/v1/meshes/{id}/intersect_all"), rays.size());
    EXPECT_EQ(logged_bytes_in(log, "/v1/meshes/{id}/distance"), kdrp.size());
    EXPECT_EQ(logged_bytes_in(log, "/v1/meshes/{id}/scan"), scan.size()) << scanned->body;
}

TEST_F(HttpFront, SceneBatchesTakeTheSharedPath) {
    // The scene query routes read their bodies as the mesh routes do: a chunked batch is admitted
    // as it arrives, and the request's bytes are counted once.
    auto cli = server_->client();
    auto created = cli->Post(
        "/v1/scenes",
        R"({"instances": [{"mesh": ")" + id_ + R"(", "transform": [1,0,0,0, 0,1,0,0, 0,0,1,0]}]})",
        "application/json");
    ASSERT_TRUE(created);
    ASSERT_EQ(created->status, 201) << created->body;
    auto doc = proto::decode_scene_json(created->body, {}, true);
    ASSERT_TRUE(doc.ok()) << created->body;
    const std::string scene = "/v1/scenes/" + doc->id;
    const std::string body = bytes_to_string(proto::encode_rays(*rays_, false));
    const std::string head = "POST " + scene +
                             "/intersect_all?max_hits=1 HTTP/1.1\r\nHost: x\r\n"
                             "Content-Type: application/x-kdrt-rays\r\n";
    const SizedAndChunked answers = post_sized_and_chunked(server_->port(), head, body);
    EXPECT_EQ(body_of(answers.chunked), body_of(answers.sized));

    ASSERT_EQ(cli->Post(scene + "/intersect", body, "application/x-kdrt-rays")->status, 200);
    const std::vector<Vec3> points = {{0, 0, 0}, {1, 2, 3}};
    const std::string kdrp = bytes_to_string(proto::encode_points(points));
    ASSERT_EQ(cli->Post(scene + "/distance", kdrp, std::string(proto::kPointMediaType))->status,
              200);
    // The access-log line is written after the answer is sent: wait for it.
    std::string log = server_->log();
    for (int i = 0; i < 3000 && log.find("route=/v1/scenes/{id}/distance ") == std::string::npos;
         ++i) {
        std::this_thread::sleep_for(10ms);
        log = server_->log();
    }
    EXPECT_EQ(logged_bytes_in(log, "/v1/scenes/{id}/intersect"), body.size());
    EXPECT_EQ(logged_bytes_in(log, "/v1/scenes/{id}/distance"), kdrp.size());
}

TEST_F(HttpFront, LongTargetsUpToTheHeadLimitAreServed) {
    // A 24 KiB query string fits the 32 KiB head limit: served, not 400/414 (issue 25 item 8).
    const std::string padding(24 << 10, 'a');
    const std::string reply = raw_exchange(
        server_->port(),
        "GET /healthz?pad=" + padding + " HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", 10s);
    EXPECT_EQ(reply.rfind("HTTP/1.1 200", 0), 0u) << reply.substr(0, 300);
    // Past the head limit: 431 naming max_request_head_bytes.
    const std::string too_long = raw_exchange(
        server_->port(),
        "GET /healthz?pad=" + std::string(40 << 10, 'a') + " HTTP/1.1\r\nHost: x\r\n\r\n", 10s);
    EXPECT_EQ(too_long.rfind("HTTP/1.1 431", 0), 0u) << too_long.substr(0, 300);
    EXPECT_NE(too_long.find("max_request_head_bytes"), std::string::npos);
}

TEST_F(HttpFront, MalformedHeadsAre400NamingWhatIsWrong) {
    const struct {
        const char* request;
        const char* detail;
    } cases[] = {
        {"GET /healthz HTTP/1.1\r\nHost: x\r\nContent-Length: 1\r\nContent-Length: 1\r\n\r\nx",
         "Content-Length"},
        {"POST /v1/meshes HTTP/1.1\r\nHost: x\r\nContent-Length: 3\r\nTransfer-Encoding: "
         "chunked\r\n\r\n",
         "both Content-Length and Transfer-Encoding"},
        {"GET /healthz HTTP/1.1\r\nHost: x\r\nX-A : b\r\n\r\n", "line 3"},
        {"GET /healthz HTTP/1.1\r\nHost: x\r\n folded\r\n\r\n", "folded"},
        {"GET /he%zzlthz HTTP/1.1\r\nHost: x\r\n\r\n", "percent escape"},
        {"GET /healthz HTTP/2.0\r\nHost: x\r\n\r\n", "HTTP version"},
        {"GET healthz HTTP/1.1\r\nHost: x\r\n\r\n", "origin form"},
        {"POST /v1/meshes HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: gzip, chunked\r\n\r\n",
         "Transfer-Encoding"},
    };
    for (const auto& c : cases) {
        const std::string reply = raw_exchange(server_->port(), c.request, 5s);
        EXPECT_EQ(reply.rfind("HTTP/1.1 400", 0), 0u) << c.request << "\n" << reply;
        EXPECT_NE(reply.find(c.detail), std::string::npos) << c.request << "\n" << reply;
        EXPECT_NE(reply.find("application/problem+json"), std::string::npos) << reply;
    }
    // The server is still there.
    auto health = server_->client()->Get("/healthz");
    ASSERT_TRUE(health);
    EXPECT_EQ(health->status, 200);
}

TEST_F(HttpFront, HeadIsAnsweredAsGetWithoutABody) {
    const std::string reply = raw_exchange(
        server_->port(), "HEAD /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", 5s);
    EXPECT_EQ(reply.rfind("HTTP/1.1 200", 0), 0u) << reply;
    EXPECT_NE(reply.find("Content-Length: 15\r\n"), std::string::npos) << reply;
    EXPECT_EQ(reply.substr(reply.find("\r\n\r\n") + 4), "");
}

TEST_F(HttpFront, EveryAnswerCarriesNoSniff) {
    // X-Content-Type-Options: nosniff, once, on every answer: routed ones of each kind and the
    // front's own refusals (issue 25 item 11).
    auto page = server_->client()->Get("/");
    ASSERT_TRUE(page);
    const std::string etag = page->get_header_value("ETag");
    const std::string rays = bytes_to_string(proto::encode_rays(*rays_, false));
    // 5000 rays: a KDRH answer over 64 KiB, sent from the route's memory.
    const std::string many =
        bytes_to_string(proto::encode_rays(random_rays(mesh_bounds(*mesh_), 5000, 4), false));
    const auto post = [&](const std::string& body) {
        return "POST /v1/meshes/" + id_ +
               "/intersect HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-kdrt-rays\r\n"
               "Connection: close\r\nContent-Length: " +
               std::to_string(body.size()) + "\r\n\r\n" + body;
    };
    const struct {
        std::string request;
        const char* status;
    } cases[] = {
        {"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", "200"},
        {"GET /v1/meshes HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", "200"},
        {"GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", "200"},
        {"HEAD /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", "200"},
        {"GET / HTTP/1.1\r\nHost: x\r\nIf-None-Match: " + etag + "\r\nConnection: close\r\n\r\n",
         "304"},
        {"GET /ui/viewer.js HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", "200"},
        {post(rays), "200"},
        {post(many), "200"},
        {post("KDRR"), "400"},
        {"GET /v2/x HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", "404"},
        {"DELETE /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", "405"},
        {"GET /he%zzlthz HTTP/1.1\r\nHost: x\r\n\r\n", "400"},  // the front's refusal
        {"GET /healthz?pad=" + std::string(40 << 10, 'a') + " HTTP/1.1\r\nHost: x\r\n\r\n", "431"},
    };
    for (const auto& c : cases) {
        SCOPED_TRACE(c.request.substr(0, 40));
        const std::string reply = raw_exchange(server_->port(), c.request, 10s);
        EXPECT_EQ(reply.rfind(std::string("HTTP/1.1 ") + c.status, 0), 0u) << reply.substr(0, 300);
        const std::string head = reply.substr(0, reply.find("\r\n\r\n") + 2);
        const size_t at = head.find("\r\nX-Content-Type-Options: nosniff\r\n");
        EXPECT_NE(at, std::string::npos) << head;
        EXPECT_EQ(head.find("X-Content-Type-Options", at + 3), std::string::npos) << head;
    }
}

TEST_F(HttpFront, Http10ClosesUnlessAskedToKeepAlive) {
    const std::string reply = raw_exchange(
        server_->port(), "GET /healthz HTTP/1.0\r\n\r\nGET /healthz HTTP/1.0\r\n\r\n", 5s);
    EXPECT_EQ(reply.rfind("HTTP/1.1 200", 0), 0u) << reply;
    EXPECT_NE(reply.find("Connection: close"), std::string::npos) << reply;
    // One answer: the connection closed after the first request.
    EXPECT_EQ(reply.find("HTTP/1.1", 1), std::string::npos) << reply;
}

}  // namespace
}  // namespace kdrt::test
