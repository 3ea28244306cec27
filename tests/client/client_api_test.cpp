// kdrt::Client against a real kdrt-server on an ephemeral loopback port: every call, its answers
// compared with the engine in process, and its errors (status, title and detail of the server's
// problem+json, local input errors, connection errors).

#include <gtest/gtest.h>

#include <cstdlib>
#include <thread>
#include <utility>

#include "client_test_util.h"
#include "fake_server.h"
#include "kdrt/proto/errors.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/problem.h"
#include "kdrt/render.h"
#include "kdrt/trace.h"

namespace kdrt::test {
namespace {

class ClientApi : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ =
            new ServerProcess({.cache_dir = dir_->path() / "cache", .args = {"--max-jobs", "4"}});
        Rng rng(test_seed());
        mesh_ = new Mesh(random_soup(rng, 3000));
        tree_ = new KdTree(build_kdtree(*mesh_));
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete mesh_;
        delete tree_;
    }
    static Client client(ClientOptions options = fast_options()) {
        return Client(server_url(*server_), std::move(options));
    }
    /// Uploads the suite's mesh and returns its id.
    static std::string uploaded() {
        auto info = client().upload(*mesh_);
        EXPECT_TRUE(info) << info.error().to_string();
        return info ? info->id : std::string();
    }

    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* mesh_;
    static KdTree* tree_;
};
TempDir* ClientApi::dir_ = nullptr;
ServerProcess* ClientApi::server_ = nullptr;
Mesh* ClientApi::mesh_ = nullptr;
KdTree* ClientApi::tree_ = nullptr;

const std::string kUnknownId(64, 'a');

TEST_F(ClientApi, UploadFromFileMeshAndBytesGivesOneId) {
    Client c = client();
    const std::string path = data_path("diplodocus.off");
    auto from_file = c.upload(path);
    ASSERT_TRUE(from_file) << from_file.error().to_string();
    const Mesh mesh = load_mesh(path);
    EXPECT_EQ(from_file->id, proto::mesh_id(mesh));
    EXPECT_EQ(from_file->triangles, mesh.triangle_count());
    EXPECT_EQ(from_file->vertices, mesh.vertex_count());
    EXPECT_GT(from_file->tree.nodes, 0u);

    auto from_mesh = c.upload(mesh);
    ASSERT_TRUE(from_mesh) << from_mesh.error().to_string();
    EXPECT_EQ(from_mesh->id, from_file->id);
    const std::vector<std::byte> ply = proto::write_mesh(mesh, proto::MeshFormat::kPly);
    auto from_bytes = c.upload(ply, proto::MeshFormat::kPly);
    ASSERT_TRUE(from_bytes) << from_bytes.error().to_string();
    EXPECT_EQ(from_bytes->id, from_file->id);
    // An explicit format overrides the extension.
    const std::filesystem::path odd = dir_->path() / "diplodocus.mesh";
    std::filesystem::copy_file(path, odd, std::filesystem::copy_options::overwrite_existing);
    auto with_format = c.upload(odd, proto::MeshFormat::kOff);
    ASSERT_TRUE(with_format) << with_format.error().to_string();
    EXPECT_EQ(with_format->id, from_file->id);
}

TEST_F(ClientApi, UploadRefusesUnusableLocalFiles) {
    Client c = client();
    auto missing = c.upload(dir_->path() / "missing.obj");
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().kind, ErrorKind::kInput);
    EXPECT_NE(missing.error().detail.find("No such file or directory"), std::string::npos)
        << missing.error().detail;
    EXPECT_NE(missing.error().detail.find("missing.obj"), std::string::npos);

    const std::filesystem::path unknown = dir_->path() / "mesh.xyz";
    write_text(unknown, "v 0 0 0\n");
    auto no_format = c.upload(unknown);
    ASSERT_FALSE(no_format);
    EXPECT_EQ(no_format.error().kind, ErrorKind::kInput);
    EXPECT_NE(no_format.error().detail.find(proto::errors::kUnknownExtension), std::string::npos);

    const std::filesystem::path dir = dir_->path() / "a_directory.obj";
    std::filesystem::create_directories(dir);
    auto directory = c.upload(dir);
    ASSERT_FALSE(directory);
    EXPECT_EQ(directory.error().kind, ErrorKind::kInput);
    EXPECT_NE(directory.error().detail.find("is a directory"), std::string::npos);

    Mesh malformed;
    malformed.positions = {0, 0, 0};
    malformed.indices = {0, 0, 7};
    auto bad_mesh = c.upload(malformed);
    ASSERT_FALSE(bad_mesh);
    EXPECT_EQ(bad_mesh.error().kind, ErrorKind::kInput);
}

TEST_F(ClientApi, BadMeshFileIsAServerErrorNamingTheLine) {
    const std::filesystem::path bad = dir_->path() / "bad.obj";
    write_text(bad, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n");
    auto info = client().upload(bad);
    ASSERT_FALSE(info);
    const Error& e = info.error();
    EXPECT_EQ(e.kind, ErrorKind::kServer);
    EXPECT_EQ(e.status, 422);
    EXPECT_EQ(e.title, "Mesh parse error");
    EXPECT_EQ(e.type, "urn:kdrt:problem:mesh-parse-error");
    EXPECT_EQ(e.line, 4u);
    EXPECT_EQ(e.detail.rfind("line 4:", 0), 0u) << e.detail;
    EXPECT_FALSE(e.request_id.empty());
    EXPECT_EQ(e.attempts, 1u);
    EXPECT_EQ(e.to_string().rfind("422 Mesh parse error: line 4:", 0), 0u) << e.to_string();

    auto empty = client().upload(std::span<const std::byte>(), proto::MeshFormat::kObj);
    ASSERT_FALSE(empty);
    EXPECT_EQ(empty.error().status, 422);
    EXPECT_EQ(empty.error().title, "Invalid mesh");
}

TEST_F(ClientApi, MeshesMeshAndRemove) {
    Client c = client();
    Rng rng(test_seed() + 5);
    const Mesh mesh = random_soup(rng, 200);
    auto info = c.upload(mesh);
    ASSERT_TRUE(info) << info.error().to_string();
    auto one = c.mesh(info->id);
    ASSERT_TRUE(one) << one.error().to_string();
    EXPECT_EQ(one->id, info->id);
    EXPECT_EQ(one->triangles, 200u);
    EXPECT_EQ(one->bounds, info->bounds);

    auto list = c.meshes();
    ASSERT_TRUE(list) << list.error().to_string();
    EXPECT_TRUE(std::is_sorted(list->begin(), list->end(),
                               [](const MeshInfo& a, const MeshInfo& b) { return a.id < b.id; }));
    EXPECT_EQ(std::count_if(list->begin(), list->end(),
                            [&](const MeshInfo& m) { return m.id == info->id; }),
              1);

    ASSERT_TRUE(c.remove(info->id));
    auto gone = c.mesh(info->id);
    ASSERT_FALSE(gone);
    EXPECT_EQ(gone.error().status, 404);
    EXPECT_EQ(gone.error().title, "Unknown mesh");
    EXPECT_NE(
        gone.error().detail.find(std::string(proto::api_errors::kUnknownMesh) + " " + info->id),
        std::string::npos);
    auto again = c.remove(info->id);
    ASSERT_FALSE(again);
    EXPECT_EQ(again.error().status, 404);
    auto list_after = c.meshes();
    ASSERT_TRUE(list_after);
    EXPECT_EQ(std::count_if(list_after->begin(), list_after->end(),
                            [&](const MeshInfo& m) { return m.id == info->id; }),
              0);
}

TEST_F(ClientApi, IdsThatAreNotIdsStayInsideTheRoute) {
    // Characters outside a path segment are escaped: "../healthz" never reaches /healthz (which
    // would answer 200 with a body that is not a mesh); the server finds no such mesh route.
    auto e = client().mesh("../healthz");
    ASSERT_FALSE(e);
    EXPECT_EQ(e.error().kind, ErrorKind::kServer);
    EXPECT_EQ(e.error().status, 404);
    auto spaced = client().mesh("not an id");
    ASSERT_FALSE(spaced);
    EXPECT_EQ(spaced.error().status, 404);
    EXPECT_EQ(spaced.error().title, "Unknown mesh");
    EXPECT_NE(spaced.error().detail.find(proto::api_errors::kBadMeshId), std::string::npos)
        << spaced.error().detail;
}

TEST_F(ClientApi, IntersectAndOccludedMatchTheEngine) {
    const std::string id = uploaded();
    Rng rng(test_seed() + 9);
    const std::vector<Ray> rays = oracle_rays(rng, *mesh_, *tree_, scaled(20'000));
    std::vector<Hit> want(rays.size());
    intersect(*tree_, rays, want);
    std::vector<uint8_t> want_occluded(rays.size());
    occluded(*tree_, rays, want_occluded);
    for (size_t chunk : {size_t{1} << 18, size_t{997}}) {
        SCOPED_TRACE(chunk);
        ClientOptions options = fast_options();
        options.chunk_rays = chunk;
        options.connections = 3;
        Client c = client(options);
        auto hits = c.intersect(id, rays);
        ASSERT_TRUE(hits) << hits.error().to_string();
        EXPECT_TRUE(same_bits(*hits, want));
        auto occ = c.occluded(id, rays);
        ASSERT_TRUE(occ) << occ.error().to_string();
        EXPECT_EQ(*occ, want_occluded);
    }
    auto none = client().intersect(id, {});
    ASSERT_TRUE(none) << none.error().to_string();
    EXPECT_TRUE(none->empty());
}

TEST_F(ClientApi, IntersectErrorsComeFromTheServer) {
    Client c = client();
    const std::vector<Ray> rays = {Ray{0, 0, -5, 0, 0, 0, 1, INFINITY}};
    auto unknown = c.intersect(kUnknownId, rays);
    ASSERT_FALSE(unknown);
    EXPECT_EQ(unknown.error().status, 404);
    EXPECT_EQ(unknown.error().title, "Unknown mesh");
    auto unknown_empty = c.occluded(kUnknownId, {});
    ASSERT_FALSE(unknown_empty);  // an empty batch still asks the server
    EXPECT_EQ(unknown_empty.error().status, 404);

    const std::string id = uploaded();
    std::vector<Ray> bad(5, rays[0]);
    bad[3].dx = NAN;
    auto refused = c.intersect(id, bad);
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().status, 400);
    EXPECT_EQ(refused.error().title, "Malformed ray batch");
    EXPECT_EQ(refused.error().code, "non_finite_ray");
    EXPECT_NE(refused.error().detail.find("ray 3: field dx is NaN"), std::string::npos)
        << refused.error().detail;
}

TEST_F(ClientApi, RenderSubmitWaitAndResultAgree) {
    const std::string id = uploaded();
    Client c = client();
    for (const char* format : {"png", "jpg", "exr"}) {
        SCOPED_TRACE(format);
        const RenderRequest request = small_render(id, Shading::kNormals, format);
        auto sync = c.render(request);
        ASSERT_TRUE(sync) << sync.error().to_string();
        auto job = c.submit(request);
        ASSERT_TRUE(job) << job.error().to_string();
        EXPECT_EQ(job->id.size(), 32u);
        EXPECT_EQ(job->mesh, id);
        std::vector<double> progress;
        std::vector<proto::JobState> states;
        auto waited = c.wait(*job, [&](const Job& status) {
            progress.push_back(status.progress);
            states.push_back(status.state);
            return true;
        });
        ASSERT_TRUE(waited) << waited.error().to_string();
        expect_same_image(*waited, *sync, format);  // renders are deterministic
        ASSERT_FALSE(states.empty());
        EXPECT_EQ(states.back(), proto::JobState::kDone);
        EXPECT_EQ(progress.back(), 1.0);
        EXPECT_TRUE(std::is_sorted(progress.begin(), progress.end()));
        auto again = c.result(*job);
        ASSERT_TRUE(again) << again.error().to_string();
        EXPECT_EQ(*again, *waited);   // the stored bytes of the same job
        ASSERT_TRUE(c.cancel(*job));  // forgets the finished job
        auto forgotten = c.job(job->id);
        ASSERT_FALSE(forgotten);
        EXPECT_EQ(forgotten.error().status, 404);
        EXPECT_EQ(forgotten.error().title, "Unknown job");
    }
    auto png = c.render(small_render(id));
    ASSERT_TRUE(png) << png.error().to_string();
    ASSERT_GE(png->size(), 8u);
    EXPECT_EQ(std::memcmp(png->data(), "\x89PNG\r\n\x1a\n", 8), 0);
}

TEST_F(ClientApi, RenderErrors) {
    Client c = client();
    auto unknown = c.render(small_render(kUnknownId));
    ASSERT_FALSE(unknown);
    EXPECT_EQ(unknown.error().status, 404);
    auto unknown_job = c.submit(small_render(kUnknownId));
    ASSERT_FALSE(unknown_job);
    EXPECT_EQ(unknown_job.error().status, 404);

    RenderRequest bad = small_render(uploaded());
    bad.settings.spp = 5000;  // over the server's max_spp (1024)
    auto refused = c.render(bad);
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().status, 400);
    EXPECT_EQ(refused.error().title, "Bad request");
    EXPECT_NE(refused.error().detail.find("1024"), std::string::npos) << refused.error().detail;

    Job ghost;
    ghost.id = std::string(32, '0');
    for (auto result : {c.job(ghost.id).ok(), c.result(ghost).ok(), c.cancel(ghost).ok()})
        EXPECT_FALSE(result);
    auto waited = c.wait(ghost);
    ASSERT_FALSE(waited);
    EXPECT_EQ(waited.error().status, 404);
    EXPECT_EQ(waited.error().title, "Unknown job");
}

TEST_F(ClientApi, WaitStopsAndCancelsWhenTheCallbackSaysSo) {
    const std::string id = uploaded();
    Client c = client();
    RenderRequest slow = small_render(id, Shading::kAo);
    slow.settings.width = 1024;
    slow.settings.height = 1024;
    slow.settings.spp = 64;
    auto job = c.submit(slow);
    ASSERT_TRUE(job) << job.error().to_string();
    int calls = 0;
    auto waited = c.wait(*job, [&](const Job&) { return ++calls < 2; });
    ASSERT_FALSE(waited);
    EXPECT_EQ(waited.error().kind, ErrorKind::kCancelled);
    EXPECT_EQ(calls, 2);
    // The job stops before its next tile.
    proto::JobState state = proto::JobState::kRunning;
    for (int i = 0; i < 600 && state != proto::JobState::kCancelled; ++i) {
        auto status = c.job(job->id);
        ASSERT_TRUE(status) << status.error().to_string();
        EXPECT_TRUE(status->cancel_requested || status->state == proto::JobState::kCancelled);
        state = status->state;
        if (state != proto::JobState::kCancelled)
            std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    EXPECT_EQ(state, proto::JobState::kCancelled);
    auto result = c.result(*job);
    ASSERT_FALSE(result);
    EXPECT_EQ(result.error().status, 409);
    EXPECT_EQ(result.error().title, "Job has no result");
    auto after = c.wait(*job);
    ASSERT_FALSE(after);
    EXPECT_EQ(after.error().kind, ErrorKind::kCancelled);
}

TEST_F(ClientApi, IdleConnectionsClosedByTheServerAreReplaced) {
    // The test server closes keep-alive connections idle for 1 s: a submission (never resent
    // after a transport error) must not go out on such a stale pooled connection.
    const std::string id = uploaded();
    Client c = client();
    ASSERT_TRUE(c.health());
    std::this_thread::sleep_for(std::chrono::milliseconds(1500));
    auto job = c.submit(small_render(id));
    ASSERT_TRUE(job) << job.error().to_string();
    auto image = c.wait(*job);
    EXPECT_TRUE(image) << image.error().to_string();
}

TEST_F(ClientApi, HealthReadyMetrics) {
    Client c = client();
    EXPECT_TRUE(c.health());
    EXPECT_TRUE(c.ready());
    auto metrics = c.metrics();
    ASSERT_TRUE(metrics) << metrics.error().to_string();
    EXPECT_NE(metrics->find("# TYPE kdrt_http_requests_total counter"), std::string::npos);
    EXPECT_NE(metrics->find("kdrt_ready 1"), std::string::npos);
}

TEST_F(ClientApi, ServerDownIsAConnectionErrorAfterTheRetries) {
    ClientOptions options = fast_options();
    options.max_retries = 2;
    Client c("http://127.0.0.1:" + std::to_string(unused_port()), options);
    auto h = c.health();
    ASSERT_FALSE(h);
    EXPECT_EQ(h.error().kind, ErrorKind::kConnection);
    EXPECT_EQ(h.error().attempts, 3u);
    EXPECT_EQ(h.error().title, "cannot connect");
    EXPECT_NE(h.error().detail.find("Connection refused"), std::string::npos) << h.error().detail;
    EXPECT_NE(h.error().detail.find("3 attempts"), std::string::npos) << h.error().detail;
    auto hits = c.intersect(kUnknownId, std::vector<Ray>(10));
    ASSERT_FALSE(hits);
    EXPECT_EQ(hits.error().kind, ErrorKind::kConnection);
}

TEST(ClientConstruction, RefusesMalformedUrlsAndOptions) {
    EXPECT_THROW(Client("ftp://127.0.0.1"), std::invalid_argument);
    EXPECT_THROW(Client("http://"), std::invalid_argument);
    EXPECT_THROW(Client("http://127.0.0.1:99999"), std::invalid_argument);
    ClientOptions zero_chunk;
    zero_chunk.chunk_rays = 0;
    EXPECT_THROW(Client("http://127.0.0.1:8080", zero_chunk), std::invalid_argument);
    ClientOptions zero_connections;
    zero_connections.connections = 0;
    EXPECT_THROW(Client("http://127.0.0.1:8080", zero_connections), std::invalid_argument);
    Client ok("127.0.0.1:8080/prefix/");
    EXPECT_EQ(ok.url().to_string(), "http://127.0.0.1:8080/prefix");
}

class ClientAuth : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ =
            new ServerProcess({.cache_dir = dir_->path() / "cache", .args = {"--token", "s3cret"}});
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
    }
    static TempDir* dir_;
    static ServerProcess* server_;
};
TempDir* ClientAuth::dir_ = nullptr;
ServerProcess* ClientAuth::server_ = nullptr;

TEST_F(ClientAuth, TokenFromOptionsOrEnvironment) {
    ::unsetenv("KDRT_TOKEN");
    Client anonymous(server_url(*server_), fast_options());
    auto refused = anonymous.meshes();
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().status, 401);
    EXPECT_EQ(refused.error().title, "Unauthorized");
    EXPECT_EQ(refused.error().attempts, 1u);  // never retried
    EXPECT_NE(refused.error().detail.find(proto::api_errors::kMissingToken), std::string::npos);
    EXPECT_TRUE(anonymous.health());  // /healthz stays open

    ClientOptions wrong = fast_options();
    wrong.token = "guess";
    auto wrong_token = Client(server_url(*server_), wrong).meshes();
    ASSERT_FALSE(wrong_token);
    EXPECT_NE(wrong_token.error().detail.find(proto::api_errors::kWrongToken), std::string::npos);

    ClientOptions right = fast_options();
    right.token = "s3cret";
    EXPECT_TRUE(Client(server_url(*server_), right).meshes());

    ::setenv("KDRT_TOKEN", "s3cret", 1);
    Client from_env(server_url(*server_), fast_options());
    ::unsetenv("KDRT_TOKEN");
    EXPECT_EQ(from_env.options().token, "s3cret");
    EXPECT_TRUE(from_env.meshes());
}

}  // namespace
}  // namespace kdrt::test
