// Operations: health, readiness, metrics, access log (text and JSON), configuration sources,
// preloading, signals, the --help/--mesh-id commands.

#include <gtest/gtest.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <thread>

#include "http_test_util.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/ray_batch.h"

namespace kdrt::test {
namespace {

/// Runs the binary with `args` to completion; returns {exit code, stdout}.
std::pair<int, std::string> run_command(const std::string& args) {
    return run_shell(std::string(KDRT_SERVER_BINARY) + " " + args);
}

TEST(HttpOps, HealthReadyAndMetrics) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    auto cli = server.client();
    auto health = cli->Get("/healthz");
    ASSERT_TRUE(health);
    EXPECT_EQ(health->status, 200);
    EXPECT_EQ(health->body, "{\"status\":\"ok\"}");
    auto ready = cli->Get("/readyz");
    ASSERT_TRUE(ready);
    EXPECT_EQ(ready->status, 200);
    EXPECT_EQ(ready->body, "{\"status\":\"ready\",\"meshes\":0}");

    const Mesh mesh = small_mesh(5);
    const std::string id = upload_id(*cli, mesh);
    const std::vector<Ray> rays = random_rays(mesh_bounds(mesh), 1000, 3);
    ASSERT_EQ(cli->Post("/v1/meshes/" + id + "/intersect",
                        bytes_to_string(proto::encode_rays(rays, false)), "application/x-kdrt-rays")
                  ->status,
              200);
    ASSERT_EQ(cli->Post("/v1/meshes/" + id + "/intersect",
                        bytes_to_string(proto::encode_rays(rays, true)), "application/x-kdrt-rays")
                  ->status,
              200);
    cli->Get("/v1/meshes/" + std::string(64, 'c'));

    auto metrics = cli->Get("/metrics");
    ASSERT_TRUE(metrics);
    ASSERT_EQ(metrics->status, 200);
    EXPECT_EQ(metrics->get_header_value("Content-Type"),
              "text/plain; version=0.0.4; charset=utf-8");
    const std::string& text = metrics->body;
    EXPECT_EQ(
        find_metric(
            text, "kdrt_http_requests_total{route=\"/v1/meshes\",method=\"POST\",status=\"201\"}"),
        1.0);
    EXPECT_EQ(find_metric(text,
                          "kdrt_http_requests_total{route=\"/v1/meshes/{id}/"
                          "intersect\",method=\"POST\",status=\"200\"}"),
              2.0);
    EXPECT_EQ(
        find_metric(
            text,
            "kdrt_http_requests_total{route=\"/v1/meshes/{id}\",method=\"GET\",status=\"404\"}"),
        1.0);
    EXPECT_EQ(find_metric(text,
                          "kdrt_http_request_duration_seconds_count{route=\"/v1/meshes/{id}/"
                          "intersect\",method=\"POST\"}"),
              2.0);
    EXPECT_EQ(find_metric(text, "kdrt_rays_traced_total{kind=\"closest\"}"), 1000.0);
    EXPECT_EQ(find_metric(text, "kdrt_rays_traced_total{kind=\"occlusion\"}"), 1000.0);
    EXPECT_EQ(find_metric(text, "kdrt_tree_builds_total"), 1.0);
    EXPECT_EQ(find_metric(text, "kdrt_tree_build_seconds_count"), 1.0);
    EXPECT_GT(find_metric(text, "kdrt_cache_bytes{where=\"memory\"}").value_or(0), 0.0);
    EXPECT_GT(find_metric(text, "kdrt_cache_bytes{where=\"disk\"}").value_or(0), 0.0);
    EXPECT_EQ(find_metric(text, "kdrt_cache_hits_total"), 2.0);
    EXPECT_EQ(find_metric(text, "kdrt_cache_misses_total"), 0.0);
    EXPECT_EQ(find_metric(text, "kdrt_cache_evictions_total"), 0.0);
    EXPECT_EQ(find_metric(text, "kdrt_ready"), 1.0);
    for (const char* family :
         {"kdrt_build_info{", "# TYPE kdrt_http_request_duration_seconds histogram",
          "# TYPE kdrt_tree_build_seconds histogram", "kdrt_jobs{state=\"queued\"} 0",
          "kdrt_jobs{state=\"running\"} 0"})
        EXPECT_NE(text.find(family), std::string::npos) << family;

    // The access log has one line per request with route, status, sizes, rays and time.
    const std::string log = server.log();
    EXPECT_NE(log.find("request method=POST route=/v1/meshes/{id}/intersect status=200 in=32016 "
                       "out=16016 rays=1000"),
              std::string::npos)
        << log;
}

TEST(HttpOps, JsonLogFormat) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache", .env = {"KDRT_LOG_FORMAT=json"}});
    server.client()->Get("/healthz");
    server.stop();
    std::istringstream lines(server.log());
    std::string line;
    int requests = 0, parsed = 0;
    while (std::getline(lines, line)) {
        const auto doc = nlohmann::json::parse(line, nullptr, false);
        ASSERT_FALSE(doc.is_discarded()) << line;
        ++parsed;
        EXPECT_TRUE(doc.contains("time") && doc.contains("level") && doc.contains("msg")) << line;
        if (doc["msg"] == "request") {
            ++requests;
            EXPECT_TRUE(doc["route"] == "/healthz" || doc["route"] == "/readyz") << line;
            if (doc["route"] == "/healthz") {
                EXPECT_EQ(doc["status"], 200);
            }
            EXPECT_TRUE(doc["ms"].is_number());
        }
    }
    EXPECT_GE(parsed, 4);
    EXPECT_GE(requests, 1);
}

TEST(HttpOps, SettingsComeFromFileThenEnvironmentThenFlags) {
    TempDir dir;
    const auto config = dir.path() / "kdrt.json";
    std::ofstream(config)
        << "{\n  // comments are allowed\n  \"memory_budget\": \"1M\",\n  \"http_threads\": 5,\n"
           "  \"max_jobs\": 3\n}\n";
    ServerProcess server({.cache_dir = dir.path() / "cache",
                          .args = {"--config", config.string(), "--http-threads", "7"},
                          .env = {"KDRT_HTTP_THREADS=6", "KDRT_MEMORY_BUDGET=2M"}});
    ASSERT_TRUE(server.running());
    EXPECT_EQ(server.metric("kdrt_cache_budget_bytes"), 2.0 * 1024 * 1024);  // env beats the file
    EXPECT_NE(server.log().find("http_threads=7"), std::string::npos)
        << server.log();  // flag beats env
}

TEST(HttpOps, MetricsAreWhatAPrometheusUserExpects) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    auto cli = server.client();
    const Mesh mesh = small_mesh(6, 2000);
    const std::string id = upload_id(*cli, mesh);
    cli->Get("/v1/meshes");
    auto render = cli->Post("/v1/render", "{\"mesh\":\"" + id + "\",\"width\":32,\"height\":16}",
                            "application/json");
    ASSERT_TRUE(render);
    ASSERT_EQ(render->status, 200) << render->body;
    // Requests the HTTP layer rejects: an invented method and a malformed request line.
    for (const char* request :
         {"BREW /v1/meshes HTTP/1.1\r\nHost: x\r\n\r\n", "NOT A REQUEST LINE\r\n\r\n"}) {
        const std::string answer = raw_exchange(server.port(), request, std::chrono::seconds(5));
        EXPECT_NE(answer.find("HTTP/1.1 400"), std::string::npos) << answer;
    }
    const std::string text = cli->Get("/metrics")->body;

    // Uploads and listings are separate series of the duration histogram.
    EXPECT_EQ(find_metric(text,
                          "kdrt_http_request_duration_seconds_count{route=\"/v1/meshes\","
                          "method=\"POST\"}"),
              1.0);
    EXPECT_EQ(find_metric(text,
                          "kdrt_http_request_duration_seconds_count{route=\"/v1/meshes\","
                          "method=\"GET\"}"),
              1.0);
    // Canonical bucket bounds.
    EXPECT_NE(text.find("le=\"0.0001\""), std::string::npos);
    for (size_t at = text.find("le=\""); at != std::string::npos; at = text.find("le=\"", at + 1)) {
        const std::string bound = text.substr(at + 4, text.find('"', at + 4) - at - 4);
        EXPECT_EQ(bound.find('e'), std::string::npos) << bound;
    }
    // Rejected requests: their own route, methods outside the standard set as "other".
    EXPECT_EQ(find_metric(text,
                          "kdrt_http_requests_total{route=\"rejected\",method=\"other\","
                          "status=\"400\"}"),
              2.0);
    EXPECT_EQ(text.find("BREW"), std::string::npos);
    // Renders count their rays and time.
    EXPECT_GE(find_metric(text, "kdrt_rays_traced_total{kind=\"render\"}").value_or(0), 512.0);
    EXPECT_EQ(find_metric(text, "kdrt_render_seconds_count"), 1.0);
    EXPECT_EQ(find_metric(text, "kdrt_job_queue_wait_seconds_count"), 0.0);
    // The standard process metrics.
    EXPECT_GT(find_metric(text, "process_resident_memory_bytes").value_or(0), 1e6);
    EXPECT_GT(find_metric(text, "process_open_fds").value_or(0), 2.0);
    EXPECT_GE(find_metric(text, "process_cpu_seconds_total").value_or(-1), 0.0);
    EXPECT_GT(find_metric(text, "process_start_time_seconds").value_or(0), 1.6e9);
    EXPECT_GT(find_metric(text, "process_max_fds").value_or(0), 0.0);

    // The rejected requests were logged with their own ids, not the previous request's.
    const std::string log = server.log();
    const size_t render_line = log.find("route=/v1/render status=200");
    const size_t rejected = log.find("method=other route=rejected status=400");
    ASSERT_NE(render_line, std::string::npos) << log;
    ASSERT_NE(rejected, std::string::npos) << log;
    const auto id_of = [&](size_t at) { return log.substr(log.find(" id=", at) + 4, 16); };
    EXPECT_NE(id_of(render_line), id_of(rejected));

    // promtool (Debian's prometheus package) accepts the exposition.
    const std::filesystem::path file = dir.path() / "metrics.txt";
    std::ofstream(file) << text;
    auto [code, out] = run_shell("promtool check metrics < '" + file.string() + "'");
    EXPECT_EQ(code, 0) << out;
}

TEST(HttpOps, MetricsCountOpenConnectionsAndBusyThreads) {
    TempDir dir;
    // No prebuffering: a request with a body gets a thread as soon as its head is in.
    ServerProcess server({.cache_dir = dir.path() / "cache",
                          .args = {"--http-threads", "4", "--request-prebuffer-bytes", "0"}});
    const auto scrape = [&] {
        const std::string answer = raw_exchange(
            server.port(), "GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
            std::chrono::seconds(10));
        return answer.substr(std::min(answer.size(), answer.find("\r\n\r\n")));
    };
    // The connection layer sees a close when its loop next runs: poll until the gauges settle.
    const auto settle = [&](double connections, double busy) {
        std::string text;
        for (int i = 0; i < 100; ++i) {
            text = scrape();
            if (find_metric(text, "kdrt_http_connections") == connections &&
                find_metric(text, "kdrt_http_threads_busy") == busy &&
                find_metric(text, "kdrt_http_threads_idle") == 4 - busy)
                break;
            std::this_thread::sleep_for(std::chrono::milliseconds(100));
        }
        return text;
    };
    // Three idle connections and one upload whose body never comes: the upload holds a thread.
    std::vector<int> idle;
    for (int i = 0; i < 3; ++i) idle.push_back(connect_loopback(server.port()));
    const int upload = connect_loopback(server.port());
    ASSERT_TRUE(send_all(upload,
                         "POST /v1/meshes HTTP/1.1\r\nHost: x\r\nContent-Type: model/stl\r\n"
                         "Content-Length: 1000000\r\n\r\nsolid x\n"));
    // The scrape itself is the fifth connection and the second busy thread.
    std::string text = settle(5, 2);
    EXPECT_EQ(find_metric(text, "kdrt_http_connections"), 5.0) << text;
    EXPECT_EQ(find_metric(text, "kdrt_http_threads_busy"), 2.0) << text;
    EXPECT_EQ(find_metric(text, "kdrt_http_threads"), 4.0) << text;
    EXPECT_EQ(find_metric(text, "kdrt_http_threads_idle"), 2.0) << text;
    EXPECT_EQ(find_metric(text, "kdrt_http_requests_waiting"), 0.0) << text;

    for (const int fd : idle) ::close(fd);
    ::close(upload);
    text = settle(1, 1);
    EXPECT_EQ(find_metric(text, "kdrt_http_connections"), 1.0) << text;
    EXPECT_EQ(find_metric(text, "kdrt_http_threads_busy"), 1.0) << text;
    EXPECT_EQ(find_metric(text, "kdrt_http_threads_idle"), 3.0) << text;
}

TEST(HttpOps, ASecondServerOnATakenPortRefusesToStart) {
    TempDir dir;
    ServerProcess first({.cache_dir = dir.path() / "cache"});
    // `timeout`: before the fix the second server started (SO_REUSEPORT) and never exited.
    auto [code, out] = run_shell("timeout 20 " + std::string(KDRT_SERVER_BINARY) +
                                 " --listen 127.0.0.1:" + std::to_string(first.port()) +
                                 " --cache-dir '" + (dir.path() / "other").string() + "'");
    EXPECT_EQ(code, 1) << out;
    EXPECT_NE(out.find("cannot listen on 127.0.0.1:" + std::to_string(first.port()) +
                       ": Address already in use"),
              std::string::npos)
        << out;
    EXPECT_EQ(first.client()->Get("/healthz")->status, 200);
}

TEST(HttpOps, BadSettingsExitWithAMessage) {
    auto [code, out] = run_command("--threads lots");
    EXPECT_EQ(code, 2);
    EXPECT_NE(out.find("--threads: \"lots\" is not a non-negative integer"), std::string::npos)
        << out;
    std::tie(code, out) = run_command("--no-such-flag 1");
    EXPECT_EQ(code, 2);
    EXPECT_NE(out.find("unknown argument \"--no-such-flag\""), std::string::npos) << out;
    std::tie(code, out) = run_command("--config /nonexistent/kdrt.json");
    EXPECT_EQ(code, 2);
    EXPECT_NE(out.find("cannot open \"/nonexistent/kdrt.json\""), std::string::npos) << out;
}

TEST(HttpOps, OutOfRangeNumbersInTheConfigAreAnErrorAndHelpStillWorks) {
    TempDir dir;
    const std::string config = (dir.path() / "kdrt.json").string();
    std::ofstream(config) << "{\"memory_budget\": 1e400}";
    // This used to abort (an uncaught nlohmann out_of_range), even with --help.
    auto [code, out] = run_command("--config " + config);
    EXPECT_EQ(code, 2) << out;
    EXPECT_NE(out.find("\"memory_budget\": number overflow"), std::string::npos) << out;
    std::tie(code, out) = run_command("--config " + config + " --help");
    EXPECT_EQ(code, 0) << out;
    EXPECT_NE(out.find("usage: kdrt-server"), std::string::npos);
    std::tie(code, out) = run_command("--memory-budget 1e400");
    EXPECT_EQ(code, 2) << out;
}

TEST(HttpOps, HelpListsEverySettingAndMeshIdPrintsIds) {
    auto [code, out] = run_command("--help");
    EXPECT_EQ(code, 0);
    for (const char* flag :
         {"--listen", "--cache-dir", "--threads", "--memory-budget", "--preload", "--token",
          "--max-upload-bytes", "--max-rays", "--max-json-rays", "--max-image-width", "--log-level",
          "--log-format", "KDRT_MEMORY_BUDGET", "--config FILE"})
        EXPECT_NE(out.find(flag), std::string::npos) << flag;
    const std::string bunny = std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off";
    std::tie(code, out) = run_command("--mesh-id " + bunny);
    EXPECT_EQ(code, 0);
    EXPECT_EQ(out, proto::mesh_id(load_bunny()) + "  " + bunny + "\n");
}

TEST(HttpOps, PreloadedMeshIsReadyAtStart) {
    TempDir dir;
    const Mesh mesh = small_mesh(8);
    const auto file = dir.path() / "soup.obj";
    std::ofstream(file, std::ios::binary) << mesh_body(mesh, proto::MeshFormat::kObj);
    ServerProcess server({.cache_dir = dir.path() / "cache", .args = {"--preload", file.string()}});
    auto res = server.client()->Get("/v1/meshes/" + proto::mesh_id(mesh));
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 200);
    EXPECT_NE(server.log().find("preloaded file=" + file.string()), std::string::npos);
    // A preload that cannot be read stops the start-up with exit code 1.
    ServerProcess broken({.cache_dir = dir.path() / "cache2",
                          .args = {"--preload", (dir.path() / "missing.obj").string()},
                          .wait_ready = false});
    EXPECT_EQ(broken.stop(0, std::chrono::seconds(30)), 1);
}

TEST(HttpOps, SigintFinishesInFlightRequestsAndExitsZero) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    auto cli = server.client();
    const Mesh mesh = small_mesh(9, 2000);
    const std::string id = upload_id(*cli, mesh);
    const std::vector<Ray> rays = random_rays(mesh_bounds(mesh), 400000, 1);
    const std::string body = bytes_to_string(proto::encode_rays(rays, false));
    std::optional<httplib::Result> in_flight;
    std::thread request([&] {
        in_flight.emplace(server.client()->Post("/v1/meshes/" + id + "/intersect", body,
                                                "application/x-kdrt-rays"));
    });
    // Wait until the request is being served, then interrupt.
    for (int i = 0;
         i < 2000 && server.log().find("route=/v1/meshes/{id}/intersect") == std::string::npos &&
         server.metric("kdrt_inflight_requests").value_or(0) < 1;
         ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
    EXPECT_EQ(server.stop(SIGINT), 0);
    request.join();
    ASSERT_TRUE(in_flight && *in_flight) << "error " << static_cast<int>(in_flight->error()) << "\n"
                                         << server.log();
    EXPECT_EQ((*in_flight)->status, 200);
    EXPECT_EQ((*in_flight)->body.size(), 16 + 16 * rays.size());
}

TEST(HttpOps, AShutdownThatCutsRequestsSaysWhichAndExitsNonZero) {
    TempDir dir;
    // No prebuffering: the connection layer hands the request to a thread at once (else it would
    // wait in the loop for the first 256 KiB of the body, not yet a request in flight).
    ServerProcess server({.cache_dir = dir.path() / "cache",
                          .args = {"--shutdown-timeout-s", "1", "--request-prebuffer-bytes", "0"}});
    // An upload whose body never finishes: admitted, then stuck reading.
    const int fd = connect_loopback(server.port());
    ASSERT_GE(fd, 0);
    const std::string head =
        "POST /v1/meshes HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-kdrt-mesh\r\n"
        "Content-Length: 1000000\r\n\r\nabcd";
    ASSERT_EQ(::send(fd, head.data(), head.size(), MSG_NOSIGNAL),
              static_cast<ssize_t>(head.size()));
    for (int i = 0; i < 5000 && server.metric("kdrt_inflight_requests").value_or(0) < 1; ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
    ASSERT_EQ(server.metric("kdrt_inflight_requests"), 1.0);
    EXPECT_EQ(server.stop(SIGTERM), 1);  // it used to exit 0 after dropping the client
    const std::string log = server.log();
    EXPECT_NE(log.find("shutdown timeout: exiting with requests still in flight"),
              std::string::npos)
        << log;
    EXPECT_NE(log.find("shutdown cut request request=\""), std::string::npos) << log;
    EXPECT_NE(log.find(" POST /v1/meshes ("), std::string::npos) << log;
    ::close(fd);
}

TEST(HttpOps, AFailedStartUpExitsAtOnceNotAfterTheShutdownTimeout) {
    TempDir dir;
    // A failed preload stops the server right after the listener thread starts; httplib's stop()
    // was a no-op until the listener ran, so some runs waited for the shutdown watchdog.
    for (int round = 0; round < 5; ++round) {
        SCOPED_TRACE(round);
        auto [code, out] =
            run_command("--listen 127.0.0.1:0 --cache-dir '" + (dir.path() / "cache").string() +
                        "' --preload /nonexistent/mesh.obj --shutdown-timeout-s 60");
        EXPECT_EQ(code, 1) << out;
        EXPECT_NE(out.find("cannot preload mesh"), std::string::npos) << out;
        EXPECT_EQ(out.find("shutdown timeout"), std::string::npos) << out;
    }
}

}  // namespace
}  // namespace kdrt::test
