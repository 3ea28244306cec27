// Memory and work bounded by configuration, against a real kdrt-server: the ray-batch byte
// budget, the finished-jobs byte budget, the render cost limit, render admission (503 +
// Retry-After), cancelling a render or a distance batch (mesh or scene) whose client left, the
// distance work limit, and the peak RSS under hostile bodies.

#include <gtest/gtest.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <fstream>
#include <iterator>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "http_test_util.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/ray_batch.h"

namespace kdrt::test {
namespace {

using namespace std::chrono_literals;
using proto::ProblemKind;

const std::string kRays(proto::kRaysMediaType);

/// The peak resident set (VmHWM) of `pid` in bytes.
uint64_t peak_rss_bytes(int pid) {
    std::ifstream in("/proc/" + std::to_string(pid) + "/status");
    std::string line;
    while (std::getline(in, line))
        if (line.rfind("VmHWM:", 0) == 0) return std::stoull(line.substr(6)) * 1024;
    return 0;
}

/// Waits (bounded) until `predicate` holds.
template <typename Predicate>
bool eventually(Predicate predicate, std::chrono::seconds limit = 60s) {
    const auto end = std::chrono::steady_clock::now() + limit;
    while (std::chrono::steady_clock::now() < end) {
        if (predicate()) return true;
        std::this_thread::sleep_for(20ms);
    }
    return predicate();
}

std::string kdrr(size_t rays, uint64_t seed) {
    return bytes_to_string(proto::encode_rays(rays_towards_unit_cube(rays, seed), false));
}

TEST(HttpAdmission, RayBatchesAreAdmittedAgainstTheByteBudget) {
    TempDir dir;
    // 90 000 bytes: a 1000-ray batch (16 + 48 x 1000) fits, a 3000-ray one never can, and a
    // second 1000-ray batch does not fit next to one in flight.
    ServerProcess server(
        {.cache_dir = dir.path() / "cache",
         .args = {"--batch-memory-budget", "90000", "--request-prebuffer-bytes", "0"}});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(3));
    const std::string path = "/v1/meshes/" + id + "/intersect";
    auto res = cli->Post(path, kdrr(1000, 1), kRays);
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 200);
    auto p = expect_problem(cli->Post(path, kdrr(3000, 2), kRays), 413);
    EXPECT_NE(p.detail.find("more than batch_memory_budget (90000)"), std::string::npos)
        << p.detail;
    // Hold a 1000-ray batch in flight: its body never finishes arriving.
    const int held = connect_loopback(server.port());
    ASSERT_GE(held, 0);
    const std::string body = kdrr(1000, 3);
    ASSERT_TRUE(send_all(held, "POST " + path + " HTTP/1.1\r\nHost: x\r\nContent-Type: " +
                                   std::string(proto::kRaysMediaType) + "\r\nContent-Length: " +
                                   std::to_string(body.size()) + "\r\n\r\n" + body.substr(0, 100)));
    ASSERT_TRUE(eventually([&] { return server.metric("kdrt_batch_bytes").value_or(0) > 0; }));
    res = cli->Post(path, kdrr(1000, 4), kRays);
    p = expect_problem(res, 503);
    EXPECT_EQ(p.kind, ProblemKind::kOverCapacity);
    EXPECT_EQ(res->get_header_value("Retry-After"), "1");
    EXPECT_NE(p.detail.find("(batch_memory_budget); this batch needs 48016"), std::string::npos)
        << p.detail;
    ::close(held);
    // The budget comes back once the held batch is gone.
    EXPECT_TRUE(eventually([&] {
        auto again = cli->Post(path, kdrr(1000, 5), kRays);
        return again && again->status == 200;
    }));
}

TEST(HttpAdmission, FinishedJobsAreForgottenOldestFirstBeyondTheirByteBudget) {
    TempDir dir;
    constexpr uint64_t kBudget = 20000;
    ServerProcess server({.cache_dir = dir.path() / "cache",
                          .args = {"--job-result-bytes", std::to_string(kBudget)}});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(4, 2000));
    std::vector<std::string> jobs;
    uint64_t total = 0;
    for (int i = 0; i < 40 && total <= kBudget; ++i) {
        const std::string json = "{\"mesh\":\"" + id +
                                 "\",\"width\":48,\"height\":48,\"seed\":" + std::to_string(i + 1) +
                                 ",\"shading\":\"ao\"}";
        auto res = cli->Post("/v1/render", {{"Prefer", "respond-async"}}, json, "application/json");
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 202) << res->body;
        const std::string job = proto::decode_job_status(res->body)->id;
        jobs.push_back(job);
        uint64_t bytes = 0;
        ASSERT_TRUE(eventually([&] {
            auto status = cli->Get("/v1/jobs/" + job);
            if (!status || status->status != 200) return false;
            auto s = proto::decode_job_status(status->body);
            bytes = s ? s->result_bytes : 0;
            return s && s->state == proto::JobState::kDone;
        }));
        ASSERT_GT(bytes, 0u);
        ASSERT_LT(bytes, kBudget);
        total += bytes;
    }
    ASSERT_GT(total, kBudget) << "the renders never filled the budget";
    // The newest job's image is kept; the oldest was forgotten to make room.
    auto newest = cli->Get("/v1/jobs/" + jobs.back() + "/result");
    ASSERT_TRUE(newest);
    EXPECT_EQ(newest->status, 200);
    auto oldest = expect_problem(cli->Get("/v1/jobs/" + jobs.front()), 404);
    EXPECT_EQ(oldest.kind, ProblemKind::kUnknownJob);
    EXPECT_LE(server.metric("kdrt_job_result_bytes").value_or(kBudget + 1), kBudget);
    EXPECT_GE(server.metric("kdrt_jobs_evicted_total").value_or(0), 1);
}

TEST(HttpAdmission, RendersOverTheCostLimitAreRefusedBeforeTheyStart) {
    TempDir dir;
    ServerProcess server(
        {.cache_dir = dir.path() / "cache", .args = {"--max-render-rays", "1000"}});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(5));
    auto ok = cli->Post("/v1/render", "{\"mesh\":\"" + id + "\",\"width\":20,\"height\":20}",
                        "application/json");
    ASSERT_TRUE(ok);
    EXPECT_EQ(ok->status, 200);
    auto p = expect_problem(
        cli->Post("/v1/render",
                  "{\"mesh\":\"" + id + "\",\"width\":20,\"height\":20,\"shading\":\"ao\"}",
                  "application/json"),
        400);
    EXPECT_EQ(p.detail,
              "render cost 6800 rays (400 pixels x 1 spp x 17 rays per sample) exceeds "
              "max_render_rays 1000");
    p = expect_problem(
        cli->Post("/v1/render", "{\"mesh\":\"" + id + "\",\"width\":20,\"height\":20,\"spp\":4}",
                  "application/json"),
        400);
    EXPECT_NE(p.detail.find("1600 rays (400 pixels x 4 spp x 1 rays per sample)"),
              std::string::npos)
        << p.detail;
}

TEST(HttpAdmission, RawRendersOverTheSizeLimitAreRefusedBeforeTheyStart) {
    TempDir dir;
    // 4 KiB: a 16 x 16 RGB raw answer (32 + 3072 bytes) fits, a 20 x 20 one (32 + 4800) not.
    ServerProcess server(
        {.cache_dir = dir.path() / "cache", .args = {"--max-raw-render-bytes", "4K"}});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(6));
    const auto render = [&](const std::string& members, bool async = false) {
        httplib::Headers headers;
        if (async) headers.emplace("Prefer", "respond-async");
        return cli->Post("/v1/render", headers, "{\"mesh\":\"" + id + "\"," + members + "}",
                         "application/json");
    };
    auto fits = render("\"width\":16,\"height\":16,\"format\":\"raw\"");
    ASSERT_TRUE(fits);
    EXPECT_EQ(fits->status, 200) << fits->body;
    EXPECT_EQ(fits->body.size(), 32u + 16 * 16 * 12);
    const double renders = server.metric("kdrt_renders_total").value_or(-1);
    EXPECT_EQ(renders, 1.0);

    auto p = expect_problem(render("\"width\":20,\"height\":20,\"format\":\"raw\""), 400);
    EXPECT_EQ(p.detail,
              "raw render answer of 4832 bytes (20 x 20 frame x 3 floats + a 32-byte header) "
              "exceeds max_raw_render_bytes 4096; ask for smaller tiles (kdrt render --split N "
              "renders a frame as N bands)");
    EXPECT_EQ(p.limit, 4096u);
    // An async raw job is refused the same way, before it is queued.
    p = expect_problem(render("\"width\":20,\"height\":20,\"format\":\"raw\"", true), 400);
    EXPECT_NE(p.detail.find("exceeds max_raw_render_bytes 4096"), std::string::npos) << p.detail;
    // The limit is checked before the mesh is looked up.
    p = expect_problem(cli->Post("/v1/render",
                                 "{\"mesh\":\"" + std::string(64, 'e') +
                                     "\",\"width\":20,\"height\":20,\"format\":\"raw\"}",
                                 "application/json"),
                       400);
    EXPECT_NE(p.detail.find("max_raw_render_bytes"), std::string::npos) << p.detail;
    // Nothing was rendered.
    EXPECT_EQ(server.metric("kdrt_renders_total").value_or(-1), renders);

    // A tile is what is answered: a 10 x 10 tile of the 20 x 20 frame fits, a 20 x 18 one not.
    auto tile = render(
        "\"width\":20,\"height\":20,\"format\":\"raw\",\"tile\":{\"x\":5,\"y\":5,\"w\":10,\"h\":"
        "10}");
    ASSERT_TRUE(tile);
    EXPECT_EQ(tile->status, 200) << tile->body;
    p = expect_problem(
        render("\"width\":20,\"height\":20,\"format\":\"raw\",\"tile\":{\"x\":0,\"y\":2,\"w\":20,"
               "\"h\":18}"),
        400);
    EXPECT_EQ(p.detail.find("raw render answer of 4352 bytes (20 x 18 tile x 3 floats"), 0u)
        << p.detail;
    // Encoded formats are not bound by it.
    for (const char* format : {"png", "exr"}) {
        auto encoded =
            render("\"width\":20,\"height\":20,\"format\":\"" + std::string(format) + "\"");
        ASSERT_TRUE(encoded);
        EXPECT_EQ(encoded->status, 200) << format << ": " << encoded->body;
    }
}

/// A render of a minute or more on this machine (4M pixels x 16 samples x 17 rays).
std::string long_render(const std::string& id) {
    return "{\"mesh\":\"" + id + "\",\"width\":2048,\"height\":2048,\"shading\":\"ao\",\"spp\":16}";
}

/// Sends a long render on a new connection (not waiting for the answer); the socket.
int start_long_render(int port, const std::string& id) {
    const int fd = connect_loopback(port);
    const std::string json = long_render(id);
    send_all(fd,
             "POST /v1/render HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
             "Content-Length: " +
                 std::to_string(json.size()) + "\r\n\r\n" + json);
    return fd;
}

TEST(HttpAdmission, ARenderWhoseClientLeftIsCancelled) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(6, 20000));
    const int fd = start_long_render(server.port(), id);
    ASSERT_GE(fd, 0);
    ASSERT_TRUE(eventually(
        [&] { return server.metric("kdrt_work_slots{work=\"render\",state=\"running\"}") == 1; }));
    ::close(fd);
    EXPECT_TRUE(eventually([&] {
        return server.log().find("render cancelled: the client closed the connection") !=
               std::string::npos;
    }));
    EXPECT_TRUE(eventually(
        [&] { return server.metric("kdrt_work_slots{work=\"render\",state=\"running\"}") == 0; }));
}

TEST(HttpAdmission, RendersBeyondTheRunningAndQueuedLimitsGet503) {
    TempDir dir;
    ServerProcess server(
        {.cache_dir = dir.path() / "cache", .args = {"--max-renders", "1", "--max-queued", "1"}});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(7, 20000));
    const int running = start_long_render(server.port(), id);
    ASSERT_TRUE(eventually(
        [&] { return server.metric("kdrt_work_slots{work=\"render\",state=\"running\"}") == 1; }));
    const int waiting = start_long_render(server.port(), id);
    ASSERT_TRUE(eventually(
        [&] { return server.metric("kdrt_work_slots{work=\"render\",state=\"waiting\"}") == 1; }));
    auto res = cli->Post("/v1/render", "{\"mesh\":\"" + id + "\",\"width\":8,\"height\":8}",
                         "application/json");
    auto p = expect_problem(res, 503);
    EXPECT_EQ(p.kind, ProblemKind::kOverCapacity);
    EXPECT_EQ(res->get_header_value("Retry-After"), "1");
    EXPECT_NE(p.detail.find("1 renders are running (max_renders) and 1 waiting (max_queued)"),
              std::string::npos)
        << p.detail;
    // Async jobs have their own queue (max_jobs) and are not shed here.
    res = cli->Post("/v1/render", {{"Prefer", "respond-async"}},
                    "{\"mesh\":\"" + id + "\",\"width\":8,\"height\":8}", "application/json");
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 202);
    ::close(waiting);
    ::close(running);
    EXPECT_TRUE(eventually([&] {
        auto again = cli->Post("/v1/render", "{\"mesh\":\"" + id + "\",\"width\":8,\"height\":8}",
                               "application/json");
        return again && again->status == 200;
    }));
}

TEST(HttpAdmission, HostileBodiesOfEveryKindStayWithinTheMemoryBound) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    ASSERT_TRUE(server.running());
    const uint64_t before = peak_rss_bytes(server.pid());
    ASSERT_GT(before, 0u);
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(8));
    // 32 MiB of nested arrays (max_json_bytes), to the DOM-parsed render route and the
    // SAX-parsed rays route: unbounded, one such body peaked at 1.36 GB.
    constexpr size_t kBody = 32u << 20;
    std::string nested(kBody, '[');
    std::fill(nested.begin() + kBody / 2, nested.end(), ']');
    // Headers and counts that promise far more than the body holds.
    std::string kdrr_lie = kdrr(1000, 9);
    kdrr_lie[8] = kdrr_lie[9] = kdrr_lie[10] = '\xff';  // a count of ~2^24 rays
    const std::string ply =
        "ply\nformat binary_little_endian 1.0\nelement vertex 134217728\nproperty float x\n"
        "property float y\nproperty float z\nelement face 134217728\nproperty list uchar int "
        "vertex_indices\nend_header\n" +
        std::string(1000, '\0');
    std::string stl(80, '\0');
    stl += std::string("\x00\x00\x00\x08", 4) + std::string(100, '\0');  // 2^27 triangles
    const std::string off = "OFF\n134217728 134217728 0\n0 0 0\n";
    std::string obj;
    while (obj.size() < kBody) obj += "f 1 2 3\n";  // faces of vertices never given
    struct Hostile {
        std::string path, body, type;
        httplib::Headers headers;
        int status;
    };
    const std::string rays_path = "/v1/meshes/" + id + "/intersect";
    const std::vector<Hostile> bodies = {
        {"/v1/render", nested, "application/json", {}, 400},
        {"/v1/render", nested, "application/json", {}, 400},
        {rays_path, nested, "application/json", {}, 400},
        {rays_path, kdrr_lie, kRays, {}, 400},
        {"/v1/meshes", ply, "application/ply", {}, 422},
        {"/v1/meshes", stl, "model/stl", {}, 422},
        {"/v1/meshes", off, "application/x-off", {}, 422},
        {"/v1/meshes", obj, "model/obj", {}, 422},
        // A 2 MB gzip body inflates to 1 GiB: refused unread.
        {"/v1/meshes",
         std::string(2u << 20, 'x'),
         "model/obj",
         {{"Content-Encoding", "gzip"}},
         415},
    };
    std::vector<int> statuses(bodies.size(), 0);
    std::vector<std::thread> senders;
    senders.reserve(bodies.size());
    for (size_t i = 0; i < bodies.size(); ++i) {
        senders.emplace_back([&, i] {
            auto c = server.client();
            const Hostile& h = bodies[i];
            auto res = c->Post(h.path, h.headers, h.body, h.type);
            statuses[i] = res ? res->status : -1;
        });
    }
    for (std::thread& t : senders) t.join();
    for (size_t i = 0; i < bodies.size(); ++i)
        EXPECT_EQ(statuses[i], bodies[i].status) << bodies[i].path << " " << bodies[i].type;
    // What the bodies themselves take in memory (3 x 32 MiB of JSON; the OBJ is spooled beyond
    // upload_memory_bytes), plus a 64 MiB margin.
    const uint64_t bound = before + 4 * uint64_t{kBody} + (64u << 20);
    EXPECT_LE(peak_rss_bytes(server.pid()), bound)
        << "peak RSS " << peak_rss_bytes(server.pid()) << " bytes, before " << before;
}

/// `count` points `far` from the origin in random directions, as a KDRP body.
std::string far_points(size_t count, float far, uint64_t seed) {
    Rng rng(seed);
    std::vector<Vec3> points(count);
    for (Vec3& p : points) p = rng.on_sphere() * far;
    return bytes_to_string(proto::encode_points(points));
}

/// The server's user + system CPU seconds (/proc/PID/stat).
double cpu_seconds(int pid) {
    std::ifstream in("/proc/" + std::to_string(pid) + "/stat");
    std::string stat((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    std::istringstream fields(stat.substr(stat.rfind(')') + 2));
    std::string field;
    double ticks = 0;
    for (int i = 3; i <= 15 && fields >> field; ++i)
        if (i == 14 || i == 15) ticks += std::stod(field);
    return ticks / static_cast<double>(::sysconf(_SC_CLK_TCK));
}

TEST(HttpAdmission, ALongDistanceBatchHoldsUpNoOtherRequest) {
    // 100000 points 1e16 away from a 20000-triangle mesh: at that distance every triangle's
    // rounded distance ties, so each point tests them all (minutes of work on two threads).
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache", .args = {"--threads", "2"}});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(10, 20000));
    const std::string body = far_points(100000, 1e16f, 11);
    const int fd = connect_loopback(server.port());
    ASSERT_GE(fd, 0);
    ASSERT_TRUE(
        send_all(fd, "POST /v1/meshes/" + id + "/distance HTTP/1.1\r\nHost: x\r\nContent-Type: " +
                         std::string(proto::kPointMediaType) +
                         "\r\nContent-Length: " + std::to_string(body.size()) + "\r\n\r\n" + body));
    // It is being computed: an HTTP thread is on it (besides the one answering /metrics) and
    // the server has spent a CPU second since.
    ASSERT_TRUE(eventually([&] { return server.metric("kdrt_http_threads_busy") == 2; }));
    const double cpu0 = cpu_seconds(server.pid());
    ASSERT_TRUE(eventually([&] { return cpu_seconds(server.pid()) > cpu0 + 1.0; }));
    // A small render and a small distance query are answered while it still runs (it once held
    // both the arena's slots, and they waited for it to finish).
    auto render = cli->Post("/v1/render", "{\"mesh\":\"" + id + "\",\"width\":8,\"height\":8}",
                            "application/json");
    ASSERT_TRUE(render);
    EXPECT_EQ(render->status, 200) << render->body;
    auto small = cli->Post("/v1/meshes/" + id + "/distance", far_points(10, 2.0f, 12),
                           std::string(proto::kPointMediaType));
    ASSERT_TRUE(small);
    EXPECT_EQ(small->status, 200) << small->body;
    auto rays = cli->Post("/v1/meshes/" + id + "/intersect", kdrr(1000, 13), kRays);
    ASSERT_TRUE(rays);
    EXPECT_EQ(rays->status, 200);
    char byte = 0;
    EXPECT_EQ(::recv(fd, &byte, 1, MSG_DONTWAIT), -1) << "the long batch was answered already";
    EXPECT_TRUE(errno == EAGAIN || errno == EWOULDBLOCK);
    // The client leaves: the batch stops.
    ::close(fd);
    EXPECT_TRUE(eventually([&] {
        return server.log().find("distance cancelled: the client closed the connection") !=
               std::string::npos;
    }));
    EXPECT_TRUE(eventually([&] { return server.metric("kdrt_http_threads_busy") == 1; }));
}

/// A scene of `count` instances of mesh `id`, each moved by (2k, 0, 0); its id.
std::string scene_of(httplib::Client& cli, const std::string& id, int count) {
    std::string body = "{\"instances\":[";
    for (int k = 0; k < count; ++k) {
        body += (k > 0 ? ",{\"mesh\":\"" : "{\"mesh\":\"") + id + "\",\"transform\":[1,0,0," +
                std::to_string(2 * k) + ",0,1,0,0,0,0,1,0]}";
    }
    auto res = cli.Post("/v1/scenes", body + "]}", "application/json");
    if (!res || res->status != 201) {
        ADD_FAILURE() << (res ? res->body : "no response");
        return {};
    }
    return res->get_header_value("Location").substr(std::string("/v1/scenes/").size());
}

TEST(HttpAdmission, DistanceWorkIsCappedBeforeAndDuringTheSearch) {
    TempDir dir;
    ServerProcess server(
        {.cache_dir = dir.path() / "cache", .args = {"--max-distance-work", "100000"}});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(14, 20000));
    const std::string type(proto::kPointMediaType);
    // A mesh and a scene of it (whose search counts each instance's work) take the same limit,
    // refused with the same problem.
    for (const std::string& path :
         {"/v1/meshes/" + id + "/distance", "/v1/scenes/" + scene_of(*cli, id, 3) + "/distance"}) {
        SCOPED_TRACE(path);
        // More points than the limit: refused before any search.
        auto p = expect_problem(cli->Post(path, far_points(100001, 2.0f, 15), type), 400);
        EXPECT_EQ(p.limit, 100000u);
        EXPECT_NE(p.detail.find("100001 points exceed max_distance_work 100000"), std::string::npos)
            << p.detail;
        // Points 1e16 away test every triangle: the search passes the limit and stops.
        p = expect_problem(cli->Post(path, far_points(1000, 1e16f, 16), type), 400);
        EXPECT_EQ(p.limit, 100000u);
        EXPECT_NE(p.detail.find("passed max_distance_work 100000 for 1000 points"),
                  std::string::npos)
            << p.detail;
        // Points near the mesh stay well within it.
        auto ok = cli->Post(path, far_points(100, 1.0f, 17), type);
        ASSERT_TRUE(ok);
        EXPECT_EQ(ok->status, 200) << ok->body;
    }
}

TEST(HttpAdmission, ASceneDistanceBatchStopsWhenTheClientLeaves) {
    // 100000 points 1e16 away from a scene of 4 instances of a 20000-triangle mesh: every point
    // tests every triangle of every instance (minutes of work on two threads).
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache", .args = {"--threads", "2"}});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string scene = scene_of(*cli, upload_id(*cli, small_mesh(10, 20000)), 4);
    const std::string body = far_points(100000, 1e16f, 19);
    const int fd = connect_loopback(server.port());
    ASSERT_GE(fd, 0);
    ASSERT_TRUE(send_all(
        fd, "POST /v1/scenes/" + scene + "/distance HTTP/1.1\r\nHost: x\r\nContent-Type: " +
                std::string(proto::kPointMediaType) +
                "\r\nContent-Length: " + std::to_string(body.size()) + "\r\n\r\n" + body));
    ASSERT_TRUE(eventually([&] { return server.metric("kdrt_http_threads_busy") == 2; }));
    const double cpu0 = cpu_seconds(server.pid());
    ASSERT_TRUE(eventually([&] { return cpu_seconds(server.pid()) > cpu0 + 1.0; }));
    char byte = 0;
    EXPECT_EQ(::recv(fd, &byte, 1, MSG_DONTWAIT), -1) << "the long batch was answered already";
    // The client leaves: the batch stops.
    ::close(fd);
    EXPECT_TRUE(eventually([&] {
        return server.log().find("distance cancelled: the client closed the connection") !=
               std::string::npos;
    }));
    EXPECT_TRUE(eventually([&] { return server.metric("kdrt_http_threads_busy") == 1; }));
}

}  // namespace
}  // namespace kdrt::test
