// Every error the API reports, with its status, problem type and detail.

#include <gtest/gtest.h>

#include <sys/socket.h>
#include <unistd.h>
#include <fstream>

#include <cmath>
#include <cstring>
#include <thread>

#include "http_test_util.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/text.h"

namespace kdrt::test {
namespace {

using proto::ProblemKind;

class HttpErrors : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ =
            new ServerProcess({.cache_dir = dir_->path() / "cache",
                               .args = {"--max-upload-bytes", "200000", "--max-rays", "1000",
                                        "--max-json-rays", "10", "--max-json-bytes", "100000"}});
        auto cli = server_->client();
        mesh_id_ = upload_id(*cli, small_mesh(3));
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
    }
    static std::string intersect_path() { return "/v1/meshes/" + mesh_id_ + "/intersect"; }

    static TempDir* dir_;
    static ServerProcess* server_;
    static std::string mesh_id_;
};
TempDir* HttpErrors::dir_ = nullptr;
ServerProcess* HttpErrors::server_ = nullptr;
std::string HttpErrors::mesh_id_;

std::string two_rays(uint16_t version = 1, uint16_t flags = 0) {
    const Ray rays[2] = {{0, 0, -5, 0, 0, 0, 1, 100}, {1, 2, 3, 0.5f, -1, 0, 0, INFINITY}};
    std::string body = bytes_to_string(proto::encode_rays(rays, false));
    std::memcpy(body.data() + 4, &version, 2);
    std::memcpy(body.data() + 6, &flags, 2);
    return body;
}

TEST_F(HttpErrors, UnknownMeshIs404) {
    auto cli = server_->client();
    const std::string absent(64, 'a');
    auto p = expect_problem(cli->Get("/v1/meshes/" + absent), 404);
    EXPECT_EQ(p.kind, ProblemKind::kUnknownMesh);
    EXPECT_EQ(p.detail, "no mesh with id " + absent);
    EXPECT_EQ(p.instance, "/v1/meshes/" + absent);
    p = expect_problem(
        cli->Post("/v1/meshes/" + absent + "/intersect", two_rays(), "application/x-kdrt-rays"),
        404);
    EXPECT_EQ(p.detail, "no mesh with id " + absent);
    p = expect_problem(cli->Get("/v1/meshes/not-an-id"), 404);
    EXPECT_NE(p.detail.find("\"not-an-id\" is not a mesh id"), std::string::npos) << p.detail;
}

TEST_F(HttpErrors, UnsupportedMediaTypeIs415) {
    auto cli = server_->client();
    auto p = expect_problem(cli->Post("/v1/meshes", "v 0 0 0", "text/plain"), 415);
    EXPECT_EQ(p.kind, ProblemKind::kUnsupportedMediaType);
    EXPECT_NE(p.detail.find("cannot tell the mesh format from Content-Type \"text/plain\""),
              std::string::npos);
    p = expect_problem(cli->Post("/v1/meshes?format=3ds", "x", "model/obj"), 415);
    EXPECT_NE(p.detail.find("unknown mesh format \"3ds\""), std::string::npos) << p.detail;
    p = expect_problem(cli->Post(intersect_path(), two_rays(), "application/octet-stream"), 415);
    EXPECT_NE(p.detail.find(proto::api_errors::kUnsupportedRayType), std::string::npos) << p.detail;
    EXPECT_NE(p.detail.find("application/octet-stream"), std::string::npos) << p.detail;
    // The connection stays usable after an early refusal (the body was drained).
    EXPECT_EQ(cli->Get("/healthz")->status, 200);
}

TEST_F(HttpErrors, MeshParseErrorsNameTheLineOrByte) {
    auto cli = server_->client();
    auto p = expect_problem(
        cli->Post("/v1/meshes", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "model/obj"), 422);
    EXPECT_EQ(p.kind, ProblemKind::kMeshParseError);
    EXPECT_EQ(p.line, 4u);
    EXPECT_EQ(p.detail.rfind("line 4:", 0), 0u) << p.detail;

    // Raw mesh whose index is out of range: the error names the byte offset.
    std::string raw = mesh_body(small_mesh(9, 1), proto::MeshFormat::kRaw);
    const uint32_t bad_index = 7;
    std::memcpy(raw.data() + raw.size() - 4, &bad_index, 4);
    p = expect_problem(cli->Post("/v1/meshes", raw, "application/x-kdrt-mesh"), 422);
    EXPECT_EQ(p.byte_offset, raw.size() - 4);
    EXPECT_EQ(p.detail.rfind("byte " + std::to_string(raw.size() - 4) + ":", 0), 0u) << p.detail;

    p = expect_problem(cli->Post("/v1/meshes", "OFF\n0 0 0\n", "application/x-off"), 422);
    EXPECT_EQ(p.kind, ProblemKind::kInvalidMesh);
    EXPECT_NE(p.detail.find(proto::api_errors::kEmptyMesh), std::string::npos) << p.detail;
}

TEST_F(HttpErrors, MalformedRayBatchesAre400WithTheReason) {
    auto cli = server_->client();
    struct Case {
        std::string body;
        const char* code;
        const char* detail;
    };
    std::string nan_ray = two_rays();
    const float nan = std::nanf("");
    std::memcpy(nan_ray.data() + 16 + 32 + 16, &nan, 4);  // ray 1, dx
    std::string magic = two_rays();
    std::memcpy(magic.data(), "ABCD", 4);
    const std::vector<Case> cases = {
        {"KDR", "too_short", "body has 3 bytes, less than the 16-byte header"},
        {magic, "bad_magic", "bad magic \"ABCD\", expected \"KDRR\""},
        {two_rays(2), "bad_version", "unsupported version 2, expected 1"},
        {two_rays(1, 2), "bad_flags", "unknown flag bits 0x0002"},
        {two_rays().substr(0, 60), "length_mismatch",
         "header says 2 rays (80 bytes) but body has 60 bytes"},
        {nan_ray, "non_finite_ray", "ray 1: field dx is NaN"},
    };
    for (const Case& c : cases) {
        SCOPED_TRACE(c.code);
        auto p =
            expect_problem(cli->Post(intersect_path(), c.body, "application/x-kdrt-rays"), 400);
        EXPECT_EQ(p.kind, ProblemKind::kBadRayBatch);
        EXPECT_EQ(p.code, c.code);
        EXPECT_NE(p.detail.find(c.detail), std::string::npos) << p.detail;
    }
}

TEST_F(HttpErrors, MalformedJsonRequestsAre400) {
    auto cli = server_->client();
    struct Case {
        std::string body;
        const char* detail;
    };
    const std::vector<Case> cases = {
        {"{\"rays\": [[0,0,0,1,0,0]", "invalid JSON at byte"},
        {"[]", "expected a JSON object, got an array"},
        {"{\"rays\": [[0,0,0,1,0]]}", "rays[0]: expected 6 or 8 numbers, got 5"},
        {"{\"rays\": [[0,0,0,1,0,0], [0,0,\"x\",1,0,0]]}",
         "rays[1][2]: expected a number, got a string"},
        {"{\"rays\": [], \"occlusion\": 1}", "\"occlusion\" must be true or false, got a number"},
        {"{\"ray\": []}", "unknown member \"ray\""},
        {"{}", "missing member \"rays\""},
        {"{\"rays\": [[1e39,0,0,1,0,0]]}", "rays[0][0] (ox): 1e39 does not fit a 32-bit float"},
    };
    for (const Case& c : cases) {
        SCOPED_TRACE(c.body);
        auto p = expect_problem(cli->Post(intersect_path(), c.body, "application/json"), 400);
        EXPECT_EQ(p.kind, ProblemKind::kBadRequest);
        EXPECT_NE(p.detail.find(c.detail), std::string::npos) << p.detail;
    }
}

TEST_F(HttpErrors, BodiesOverTheLimitsAre413) {
    auto cli = server_->client();
    // Upload over --max-upload-bytes 200000.
    auto p = expect_problem(cli->Post("/v1/meshes", std::string(200001, ' '), "model/obj"), 413);
    EXPECT_EQ(p.kind, ProblemKind::kPayloadTooLarge);
    EXPECT_EQ(p.limit, 200000u);
    EXPECT_NE(p.detail.find("request body exceeds the limit of 200000 bytes"), std::string::npos)
        << p.detail;
    // KDRR over --max-rays 1000: by the body size first...
    const std::vector<Ray> many(1001, Ray{0, 0, 0, 0, 1, 0, 0, 1});
    cli = server_->client();
    p = expect_problem(cli->Post(intersect_path(), bytes_to_string(proto::encode_rays(many, false)),
                                 "application/x-kdrt-rays"),
                       413);
    EXPECT_EQ(p.limit, 16u + 32u * 1000u);
    // ...and by the header count when the body is small.
    cli = server_->client();
    std::string header = two_rays().substr(0, 16);
    const uint32_t count = 5000;
    std::memcpy(header.data() + 8, &count, 4);
    p = expect_problem(cli->Post(intersect_path(), header, "application/x-kdrt-rays"), 413);
    EXPECT_EQ(p.code, "too_many_rays");
    EXPECT_NE(p.detail.find("header says 5000 rays, limit is 1000"), std::string::npos) << p.detail;
    // JSON over --max-json-rays 10.
    const std::vector<Ray> eleven(11, Ray{0, 0, 0, 0, 1, 0, 0, 1});
    p = expect_problem(
        cli->Post(intersect_path(), proto::encode_json_rays(eleven, false), "application/json"),
        413);
    EXPECT_EQ(p.limit, 10u);
    EXPECT_NE(p.detail.find("rays[10]: rays in a JSON batch exceed the limit of 10"),
              std::string::npos)
        << p.detail;
    // JSON body over --max-json-bytes.
    cli = server_->client();
    p = expect_problem(cli->Post(intersect_path(), std::string(100001, ' '), "application/json"),
                       413);
    EXPECT_EQ(p.limit, 100000u);
}

TEST_F(HttpErrors, UnknownRoutesAndMethods) {
    auto cli = server_->client();
    auto missing = cli->Get("/v2/meshes");
    auto p = expect_problem(missing, 404);
    EXPECT_EQ(p.kind, ProblemKind::kNotFound);
    // The path once, as the instance (issue 25 item 11).
    EXPECT_EQ(p.detail, "no route for GET at this path");
    EXPECT_EQ(p.instance, "/v2/meshes");
    EXPECT_EQ(missing->body.find("/v2/meshes"), missing->body.rfind("/v2/meshes")) << missing->body;
    auto res = cli->Put("/v1/meshes", "x", "text/plain");
    p = expect_problem(res, 405);
    EXPECT_EQ(p.detail, "this path does not support method PUT (allowed: POST, GET)");
    EXPECT_EQ(p.kind, ProblemKind::kMethodNotAllowed);
    EXPECT_EQ(res->get_header_value("Allow"), "POST, GET");
    p = expect_problem(cli->Post("/healthz", "x", "text/plain"), 405);
    EXPECT_NE(p.detail.find("does not support method POST (allowed: GET)"), std::string::npos)
        << p.detail;
}

TEST_F(HttpErrors, ABlender247PlyLoadsWithAWarningInTheAnswer) {
    std::ifstream in(std::string(KDRT_TEST_DATA_DIR) + "/quirks/blender247.ply", std::ios::binary);
    const std::string ply{std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
    ASSERT_FALSE(ply.empty());
    auto res = server_->client()->Post("/v1/meshes", ply, "application/ply");
    ASSERT_TRUE(res);
    ASSERT_TRUE(res->status == 201 || res->status == 200) << res->body;
    auto summary = proto::decode_mesh_summary(res->body);
    ASSERT_TRUE(summary) << res->body;
    EXPECT_EQ(summary->triangles, 1u);
    ASSERT_EQ(summary->warnings.size(), 1u) << res->body;
    EXPECT_EQ(summary->warnings[0],
              "line 3: PLY header line with unknown keyword 'Created' skipped");
    // Not stored: the mesh's own summary has no warnings.
    EXPECT_EQ(server_->client()->Get("/v1/meshes/" + summary->id)->body.find("warnings"),
              std::string::npos);
}

TEST_F(HttpErrors, InvalidContentLengthsAreRefused) {
    for (const char* value : {"abc", "1, 2", "0x10", "-1", "+5", "99999999999999999999"}) {
        SCOPED_TRACE(value);
        const std::string answer = raw_exchange(
            server_->port(),
            std::string("POST /v1/meshes HTTP/1.1\r\nHost: x\r\nContent-Type: model/stl\r\n"
                        "Connection: close\r\nContent-Length: ") +
                value + "\r\n\r\n",
            std::chrono::seconds(5));
        EXPECT_EQ(answer.rfind("HTTP/1.1 400", 0), 0u) << answer;
        EXPECT_NE(answer.find("invalid Content-Length"), std::string::npos) << answer;
    }
    const std::string twice = raw_exchange(
        server_->port(),
        "POST /v1/meshes HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Length: 3\r\n"
        "Content-Length: 3\r\n\r\nabc",
        std::chrono::seconds(5));
    EXPECT_EQ(twice.rfind("HTTP/1.1 400", 0), 0u) << twice;
}

TEST_F(HttpErrors, PostWithoutContentLengthIsRefusedAtOnce) {
    const std::string reply = raw_exchange(
        server_->port(), "POST /v1/meshes HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
        std::chrono::seconds(10));
    EXPECT_EQ(reply.rfind("HTTP/1.1 400", 0), 0u) << reply;
    EXPECT_NE(reply.find("a POST needs a Content-Length (or chunked) body"), std::string::npos)
        << reply;
}

TEST_F(HttpErrors, ExpectContinueIsRefusedBeforeTheBodyIsSent) {
    // The client announces 1 GB and waits for "100 Continue"; the server answers 413 at once.
    const std::string reply =
        raw_exchange(server_->port(),
                     "POST /v1/meshes HTTP/1.1\r\nHost: x\r\nContent-Type: model/obj\r\n"
                     "Content-Length: 1000000000\r\nExpect: 100-continue\r\n\r\n",
                     std::chrono::seconds(10));
    EXPECT_EQ(reply.rfind("HTTP/1.1 413", 0), 0u) << reply;
    EXPECT_NE(reply.find("application/problem+json"), std::string::npos) << reply;
    EXPECT_NE(reply.find("request body exceeds the limit of 200000 bytes"), std::string::npos)
        << reply;
    EXPECT_EQ(reply.find("100 Continue"), std::string::npos) << reply;
}

TEST(HttpEcho, HugeRequestValuesAreQuotedByAShortPrefix) {
    // A 32 MiB value where a short word is expected: the refusal quotes 64 bytes of it and its
    // length (it once came back whole, a 32 MiB answer per request).
    TempDir dir;
    ServerProcess server(
        {.cache_dir = dir.path() / "cache", .args = {"--max-json-bytes", "40000000"}});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(4));
    // A new connection for each request. On a kept-alive one, a 32 MiB POST races the server's
    // idle timeout (1 s here, ServerProcess): httplib checks that the connection is alive, copies
    // the whole request (the body included) and only then writes its first byte, so a loaded
    // machine can stall past the timeout in between; the server then rightly closes the idle
    // connection (RFC 9112 9.5), and the POST, not retried, fails with "Failed to write
    // connection" (seen on Debian 13's check under load; the client's write saw EOF 1.8 s after
    // the previous answer).
    cli->set_keep_alive(false);
    const std::string huge(32u << 20, 'x');
    const std::string quoted = proto::in_quotes(std::string(64, 'x')) + "... (33554432 bytes)";
    struct Case {
        std::string path, body;
    };
    const std::string mesh = "{\"mesh\":\"" + id + "\",\"width\":8,\"height\":8,";
    const std::string scan = "/v1/meshes/" + id + "/scan";
    const std::vector<Case> cases = {
        {"/v1/render", mesh + "\"shading\":\"" + huge + "\"}"},
        {"/v1/render", mesh + "\"format\":\"" + huge + "\"}"},
        {"/v1/render", mesh + "\"" + huge + "\":1}"},
        {scan,
         "{\"format\":\"" + huge + "\",\"lidar\":{\"elevation_deg\":[0],\"azimuth_steps\":4}}"},
        {scan,
         "{\"pinhole\":{\"camera\":{\"eye\":[0,0,-5],\"look_at\":[0,0,0],\"fov\":50},"
         "\"width\":4,\"height\":4,\"output\":\"" +
             huge + "\"}}"},
        {"/v1/meshes/" + id + "/intersect", "{\"" + huge + "\":[]}"},
    };
    for (const Case& c : cases) {
        SCOPED_TRACE(c.path + " " + c.body.substr(0, 90));
        auto res = cli->Post(c.path, c.body, "application/json");
        auto p = expect_problem(res, 400);
        if (!res) continue;  // expect_problem has failed the test
        EXPECT_NE(p.detail.find(quoted), std::string::npos) << p.detail.substr(0, 300);
        EXPECT_LT(res->body.size(), 2048u);
    }
    // A long header value in a refusal (4000 bytes: the HTTP layer takes lines up to 8 KiB): the
    // same.
    auto res =
        cli->Post("/v1/meshes/" + id + "/distance", {}, "", "application/" + huge.substr(0, 3988));
    auto p = expect_problem(res, 415);
    EXPECT_NE(p.detail.find("... (4000 bytes)"), std::string::npos) << p.detail.substr(0, 300);
    EXPECT_LT(res->body.size(), 2048u);
}

TEST(HttpStartup, V1IsUnavailableUntilTheIndexAndPreloadsAreDone) {
    TempDir dir;
    const std::string bunny =
        std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off";  // a build of some 100 ms
    ServerProcess server(
        {.cache_dir = dir.path() / "cache", .args = {"--preload", bunny}, .wait_ready = false});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    auto ready = cli->Get("/readyz");
    ASSERT_TRUE(ready);
    EXPECT_EQ(cli->Get("/healthz")->status, 200);  // alive from the start
    if (ready->status == 200) GTEST_SKIP() << "the preload finished before the first probe";
    auto p = expect_problem(ready, 503);
    EXPECT_EQ(p.kind, ProblemKind::kNotReady);
    auto res = cli->Get("/v1/meshes");
    if (res && res->status == 503) {
        p = expect_problem(res, 503);
        EXPECT_EQ(p.kind, ProblemKind::kNotReady);
        EXPECT_EQ(res->get_header_value("Retry-After"), "1");
    }
    for (int i = 0; i < 12000 && cli->Get("/readyz")->status != 200; ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    EXPECT_EQ(cli->Get("/readyz")->status, 200);
    EXPECT_EQ(cli->Get("/v1/meshes")->status, 200);
}

TEST(HttpCapacity, OverCapacityIs503WithRetryAfter) {
    TempDir dir;
    // No prebuffering: the held upload below gets a thread (and its slot) with its head.
    ServerProcess server({.cache_dir = dir.path() / "cache",
                          .args = {"--max-inflight", "1", "--request-prebuffer-bytes", "0"}});
    ASSERT_TRUE(server.running());
    // Hold the only slot: an upload whose body never finishes arriving.
    const int held = connect_loopback(server.port());
    ASSERT_GE(held, 0);
    const std::string head =
        "POST /v1/meshes HTTP/1.1\r\nHost: x\r\nContent-Type: model/obj\r\nContent-Length: "
        "100\r\n\r\nv 0";
    ASSERT_EQ(::send(held, head.data(), head.size(), MSG_NOSIGNAL),
              static_cast<ssize_t>(head.size()));
    // No probe before the held upload has its slot: on a loaded machine a probe could reach the
    // gate first, and the held upload, refused, would wait for the rest of its body (it is
    // drained before its answer), never holding the slot (seen on Debian 13's check).
    for (int i = 0; i < 5000 && server.metric("kdrt_inflight_requests").value_or(0) < 1; ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
    ASSERT_EQ(server.metric("kdrt_inflight_requests"), 1.0);
    auto cli = server.client();
    auto res = cli->Post("/v1/meshes", "v 0 0 0\n", "model/obj");
    auto p = expect_problem(res, 503);
    EXPECT_EQ(p.kind, ProblemKind::kOverCapacity);
    EXPECT_EQ(res->get_header_value("Retry-After"), "1");
    EXPECT_EQ(p.retry_after, 1u);
    EXPECT_NE(p.detail.find("1 requests are in flight (max_inflight)"), std::string::npos)
        << p.detail;
    // Light routes are not gated.
    EXPECT_EQ(cli->Get("/v1/meshes")->status, 200);
    ::close(held);
    // The slot comes back once the held request ends.
    bool recovered = false;
    for (int attempt = 0; attempt < 500 && !recovered; ++attempt) {
        auto again = cli->Post("/v1/meshes", "v 0 0 0\n", "model/obj");
        recovered = again && again->status == 422;
        if (!recovered) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    EXPECT_TRUE(recovered);
}

TEST(HttpAuth, BearerTokenGuardsV1Only) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache", .args = {"--token", "s3cret"}});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    auto res = cli->Get("/v1/meshes");
    auto p = expect_problem(res, 401);
    EXPECT_EQ(p.kind, ProblemKind::kUnauthorized);
    EXPECT_EQ(res->get_header_value("WWW-Authenticate"), "Bearer realm=\"kdrt\"");
    EXPECT_NE(p.detail.find("requires an Authorization: Bearer token"), std::string::npos)
        << p.detail;
    cli->set_bearer_token_auth("wrong");
    p = expect_problem(cli->Post("/v1/meshes", "v 0 0 0\n", "model/obj"), 401);
    EXPECT_NE(p.detail.find("bearer token is not valid"), std::string::npos) << p.detail;
    cli->set_bearer_token_auth("s3cret");
    EXPECT_EQ(cli->Get("/v1/meshes")->status, 200);
    EXPECT_EQ(upload_id(*cli, small_mesh(1)).size(), 64u);
    // The scheme is case-insensitive (RFC 9110 11.1) and may be followed by several spaces; a
    // scheme that merely starts with "bearer" is not it.
    for (const char* value : {"bearer s3cret", "BEARER s3cret", "BeArEr   s3cret"}) {
        auto other = server.client();
        auto r = other->Get("/v1/meshes", {{"Authorization", value}});
        ASSERT_TRUE(r);
        EXPECT_EQ(r->status, 200) << value;
    }
    for (const char* value : {"Bearers3cret", "Basic s3cret", "bearer", "bearer "}) {
        auto other = server.client();
        expect_problem(other->Get("/v1/meshes", {{"Authorization", value}}), 401);
    }
    // Health and metrics stay open.
    auto open = server.client();
    EXPECT_EQ(open->Get("/healthz")->status, 200);
    EXPECT_EQ(open->Get("/readyz")->status, 200);
    EXPECT_EQ(open->Get("/metrics")->status, 200);
}

TEST(HttpAuth, TokenRolesGuardEachRouteClass) {
    TempDir dir;
    const std::filesystem::path tokens = dir.path() / "tokens";
    std::ofstream(tokens) << "# role token\n"
                             "read viewer-t0ken-0123456789\n"
                             "write uploader-t0ken-0123456789\r\n"
                             "\n"
                             "  read,write   admin-t0ken-0123456789  \n";
    std::filesystem::permissions(tokens, std::filesystem::perms::owner_read |
                                             std::filesystem::perms::owner_write |
                                             std::filesystem::perms::group_read);
    ServerProcess server({.cache_dir = dir.path() / "cache",
                          .args = {"--token", "full-t0ken", "--tokens-file", tokens.string()}});
    ASSERT_TRUE(server.running());
    // A tokens file the group may read is taken, with a warning in the log at start-up.
    EXPECT_NE(server.log().find("tokens_file \"" + tokens.string() +
                                "\" can be read by users other than its owner (mode 0640)"),
              std::string::npos)
        << server.log();
    const auto as = [&](const std::string& token) {
        auto cli = server.client();
        cli->set_bearer_token_auth(token);
        return cli;
    };
    const auto forbidden = [](const httplib::Result& res, const std::string& route,
                              const std::string& role, const std::string& held) {
        auto p = expect_problem(res, 403);
        EXPECT_EQ(p.kind, ProblemKind::kForbidden);
        EXPECT_EQ(p.code, role);
        EXPECT_EQ(p.detail, route + " needs a token with the role " + role +
                                "; this token has the role " + held);
        EXPECT_EQ(res->get_header_value("WWW-Authenticate"),
                  "Bearer realm=\"kdrt\", error=\"insufficient_scope\", scope=\"" + role + "\"");
    };
    auto viewer = as("viewer-t0ken-0123456789"), uploader = as("uploader-t0ken-0123456789"),
         admin = as("admin-t0ken-0123456789");
    auto full = as("full-t0ken");

    // Writes: the write role (and the single `token`, which has both roles).
    const Mesh mesh = small_mesh(3, 300);
    forbidden(upload(*viewer, mesh), "POST /v1/meshes", "write", "read");
    const std::string id = upload_id(*uploader, mesh);
    ASSERT_EQ(id.size(), 64u);
    EXPECT_EQ(upload_id(*full, small_mesh(4, 300)).size(), 64u);
    const std::string other = upload_id(*admin, small_mesh(5, 300));
    forbidden(viewer->Delete("/v1/meshes/" + id), "DELETE /v1/meshes/{id}", "write", "read");

    // Reads, traces, renders and jobs: the read role.
    const std::string render = "{\"mesh\":\"" + id + "\",\"width\":16,\"height\":8}";
    for (auto* cli : {viewer.get(), admin.get(), full.get()}) {
        EXPECT_EQ(cli->Get("/v1/meshes")->status, 200);
        EXPECT_EQ(cli->Get("/v1/meshes/" + id)->status, 200);
        EXPECT_EQ(trace(*cli, id, random_rays(mesh_bounds(mesh), 16, 1))->status, 200);
        EXPECT_EQ(cli->Post("/v1/render", render, "application/json")->status, 200);
    }
    auto job =
        viewer->Post("/v1/render", {{"Prefer", "respond-async"}}, render, "application/json");
    ASSERT_EQ(job->status, 202) << job->body;
    const std::string job_path = "/v1/jobs/" + proto::decode_job_status(job->body)->id;
    EXPECT_EQ(viewer->Get(job_path)->status, 200);
    forbidden(uploader->Get(job_path), "GET /v1/jobs/{id}", "read", "write");
    forbidden(uploader->Get("/v1/meshes"), "GET /v1/meshes", "read", "write");
    forbidden(uploader->Get("/v1/meshes/" + id), "GET /v1/meshes/{id}", "read", "write");
    forbidden(trace(*uploader, id, random_rays(mesh_bounds(mesh), 16, 1)),
              "POST /v1/meshes/{id}/intersect", "read", "write");
    forbidden(uploader->Post("/v1/render", render, "application/json"), "POST /v1/render", "read",
              "write");
    EXPECT_NE(viewer->Delete(job_path)->status, 403);

    // The refused deletion left the mesh; the write role deletes.
    EXPECT_EQ(viewer->Get("/v1/meshes/" + id)->status, 200);
    EXPECT_EQ(uploader->Delete("/v1/meshes/" + id)->status, 204);
    EXPECT_EQ(admin->Delete("/v1/meshes/" + other)->status, 204);
    EXPECT_EQ(viewer->Get("/v1/meshes/" + id)->status, 404);

    // A token not in the file is still 401; an upload refused for its role is refused before
    // its body is sent (Expect: 100-continue).
    expect_problem(as("admin-t0ken-012345678")->Get("/v1/meshes"), 401);
    const std::string answer = raw_exchange(
        server.port(),
        "POST /v1/meshes HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer viewer-t0ken-0123456789\r\n"
        "Content-Type: model/obj\r\nContent-Length: 100000\r\nExpect: 100-continue\r\n\r\n",
        std::chrono::seconds(10));
    EXPECT_EQ(answer.rfind("HTTP/1.1 403", 0), 0u) << answer;
    EXPECT_EQ(answer.find("100 Continue"), std::string::npos) << answer;
    EXPECT_NE(answer.find("POST /v1/meshes needs a token with the role write"), std::string::npos)
        << answer;
}

}  // namespace
}  // namespace kdrt::test
