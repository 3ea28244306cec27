// kdrt-server-bench: the server's performance numbers (issue "kdrt-server", Performance).
// Starts the real kdrt-server on an ephemeral loopback port and measures, in one run:
//   - upload-to-ready of the bunny and of a 1M-triangle mesh (POST until the 201 arrives),
//   - 1M-ray primary and diffuse batches over loopback HTTP (KDRR -> KDRH) against the same rays
//     traced in process with the same thread count, as Mrays/s and their ratio,
//   - 1-ray and 1k-ray intersect latency over one keep-alive connection (p50, p99),
//   - 1024^2 eyelight render latency over HTTP.
// Prints one JSON object per measurement; "server_side_ms" is the server's own time for the
// request (its access log: headers read to response written), the rest of "http_ms" is the client. Not a ctest test (a
// benchmark asserts nothing).
//
//   kdrt-server-bench [--threads N] [--reps R] [--latency-requests K] [--server PATH]

#include <fcntl.h>
#include <httplib.h>
#include <signal.h>
#include <sys/wait.h>
#include <tbb/task_arena.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/raygen.h"
#include "kdrt/trace.h"

namespace {

using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;

double seconds_since(Clock::time_point start) { return std::chrono::duration<double>(Clock::now() - start).count(); }

std::string as_string(const std::vector<std::byte>& bytes) {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

double percentile(std::vector<double> values, double p) {
    std::sort(values.begin(), values.end());
    const size_t index = std::min(values.size() - 1, static_cast<size_t>(p * static_cast<double>(values.size())));
    return values[index];
}

/// A torus of rings x sides quads (2 triangles each): a closed, smooth 1M-triangle test mesh.
kdrt::Mesh torus(uint32_t rings, uint32_t sides) {
    kdrt::Mesh m;
    for (uint32_t i = 0; i < rings; ++i) {
        const float u = 6.2831853f * static_cast<float>(i) / static_cast<float>(rings);
        for (uint32_t j = 0; j < sides; ++j) {
            const float v = 6.2831853f * static_cast<float>(j) / static_cast<float>(sides);
            const float r = 1.0f + 0.35f * std::cos(v);
            m.positions.push_back(r * std::cos(u));
            m.positions.push_back(0.35f * std::sin(v));
            m.positions.push_back(r * std::sin(u));
        }
    }
    for (uint32_t i = 0; i < rings; ++i) {
        for (uint32_t j = 0; j < sides; ++j) {
            const uint32_t a = i * sides + j, b = ((i + 1) % rings) * sides + j;
            const uint32_t c = ((i + 1) % rings) * sides + (j + 1) % sides, d = i * sides + (j + 1) % sides;
            m.indices.insert(m.indices.end(), {a, b, c, a, c, d});
        }
    }
    return m;
}

struct Server {
    pid_t pid = -1;
    int port = 0;
    fs::path dir;

    Server(const std::string& binary, unsigned threads) {
        dir = fs::temp_directory_path() / ("kdrt-server-bench-" + std::to_string(::getpid()));
        fs::remove_all(dir);
        fs::create_directories(dir);
        const std::string port_file = (dir / "port").string(), cache = (dir / "cache").string();
        const std::string log = (dir / "server.log").string();
        const std::string t = std::to_string(threads);
        pid = ::fork();
        if (pid == 0) {
            const int log_fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
            ::dup2(log_fd, 2);
            ::execl(binary.c_str(), binary.c_str(), "--listen", "127.0.0.1:0", "--port-file", port_file.c_str(),
                    "--cache-dir", cache.c_str(), "--threads", t.c_str(), "--max-inflight", "1000",
                    static_cast<char*>(nullptr));
            ::_exit(127);
        }
        for (int i = 0; i < 6000 && port == 0; ++i) {
            std::ifstream in(port_file);
            if (!(in >> port)) std::this_thread::sleep_for(std::chrono::milliseconds(10));
        }
        httplib::Client cli("127.0.0.1", port);
        for (int i = 0; i < 6000; ++i) {
            auto res = cli.Get("/readyz");
            if (res && res->status == 200) return;
            std::this_thread::sleep_for(std::chrono::milliseconds(10));
        }
        std::fprintf(stderr, "kdrt-server-bench: the server did not start\n");
        std::exit(1);
    }
    /// The server's own time (from its access log) of the fastest request with `rays` rays.
    double fastest_logged_ms(size_t rays) const {
        std::ifstream in(dir / "server.log");
        std::string line;
        double best = 1e30;
        const std::string key = "rays=" + std::to_string(rays) + " ms=";
        while (std::getline(in, line)) {
            const size_t at = line.find(key);
            if (at != std::string::npos && line.find("/intersect") != std::string::npos)
                best = std::min(best, std::stod(line.substr(at + key.size())));
        }
        return best;
    }

    ~Server() {
        ::kill(pid, SIGTERM);
        int status = 0;
        ::waitpid(pid, &status, 0);
        fs::remove_all(dir);
    }
};

std::unique_ptr<httplib::Client> client(int port) {
    auto cli = std::make_unique<httplib::Client>("127.0.0.1", port);
    cli->set_keep_alive(true);
    cli->set_tcp_nodelay(true);
    cli->set_read_timeout(600, 0);
    cli->set_write_timeout(600, 0);
    return cli;
}

/// POST the raw mesh; returns seconds until the 201/200 answer and the id.
std::pair<double, std::string> upload(httplib::Client& cli, const kdrt::Mesh& mesh) {
    const std::string body = as_string(kdrt::proto::write_mesh(mesh, kdrt::proto::MeshFormat::kRaw));
    const auto start = Clock::now();
    auto res = cli.Post("/v1/meshes", body, "application/x-kdrt-mesh");
    const double s = seconds_since(start);
    if (!res || (res->status != 201 && res->status != 200)) {
        std::fprintf(stderr, "upload failed: %d %s\n", res ? res->status : -1, res ? res->body.c_str() : "");
        std::exit(1);
    }
    return {s, kdrt::proto::mesh_id(mesh)};
}

/// One POST of a KDRR body, the KDRH answer received into a pre-sized buffer.
double trace_remote(httplib::Client& cli, const std::string& path, const std::string& body, size_t answer_bytes,
                    std::string& answer) {
    answer.clear();
    answer.reserve(answer_bytes);
    const auto start = Clock::now();
    auto res = cli.Post(path, body, "application/x-kdrt-rays");
    const double s = seconds_since(start);
    if (!res || res->status != 200) {
        std::fprintf(stderr, "intersect failed: %d\n", res ? res->status : -1);
        std::exit(1);
    }
    answer = std::move(res->body);
    return s;
}

}  // namespace

int main(int argc, char** argv) {
    unsigned threads = std::max(1u, std::thread::hardware_concurrency());
    int reps = 5;
    int latency_requests = 2000;
    std::string binary = KDRT_SERVER_BINARY;
    for (int i = 1; i + 1 < argc; i += 2) {
        const std::string flag = argv[i];
        if (flag == "--threads")
            threads = static_cast<unsigned>(std::stoul(argv[i + 1]));
        else if (flag == "--reps")
            reps = std::stoi(argv[i + 1]);
        else if (flag == "--latency-requests")
            latency_requests = std::stoi(argv[i + 1]);
        else if (flag == "--server")
            binary = argv[i + 1];
        else {
            std::fprintf(stderr,
                         "usage: kdrt-server-bench [--threads N] [--reps R] [--latency-requests K] [--server PATH]\n");
            return 2;
        }
    }
    auto bunny = kdrt::proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
    if (!bunny) {
        std::fprintf(stderr, "%s\n", bunny.error().to_string().c_str());
        return 1;
    }
    Server server(binary, threads);
    auto cli = client(server.port);

    // Upload-to-ready.
    const auto [bunny_s, bunny_id] = upload(*cli, *bunny);
    std::printf("{\"measure\":\"upload_to_ready\",\"mesh\":\"bunny\",\"triangles\":%zu,\"ms\":%.1f}\n",
                bunny->triangle_count(), bunny_s * 1e3);
    {
        const kdrt::Mesh big = torus(1000, 500);
        const auto [big_s, big_id] = upload(*cli, big);
        std::printf("{\"measure\":\"upload_to_ready\",\"mesh\":\"torus\",\"triangles\":%zu,\"ms\":%.1f}\n",
                    big.triangle_count(), big_s * 1e3);
        cli->Delete(("/v1/meshes/" + big_id).c_str());
    }
    std::fflush(stdout);

    // Throughput: the same rays in process and over HTTP, alternating, best of `reps`.
    tbb::task_arena arena(static_cast<int>(threads));
    const kdrt::KdTree tree = arena.execute([&] { return kdrt::build_kdtree(*bunny); });
    const std::string path = "/v1/meshes/" + bunny_id + "/intersect";
    for (const kdrt::RayKind kind : {kdrt::RayKind::kPrimary, kdrt::RayKind::kDiffuse}) {
        const std::vector<kdrt::Ray> rays =
            arena.execute([&] { return kdrt::generate_rays(tree, {.kind = kind, .res = 1024, .seed = 1}); });
        const std::string body = as_string(kdrt::proto::encode_rays(rays, false));
        std::vector<kdrt::Hit> hits(rays.size());
        std::string answer;
        double best_local = 1e30, best_remote = 1e30;
        for (int r = 0; r < reps; ++r) {
            const auto start = Clock::now();
            arena.execute([&] { kdrt::intersect(tree, rays, hits); });
            best_local = std::min(best_local, seconds_since(start));
            best_remote = std::min(best_remote, trace_remote(*cli, path, body, 16 + 16 * rays.size(), answer));
        }
        const bool same = answer == as_string(kdrt::proto::encode_hits(hits));
        const double local = static_cast<double>(rays.size()) / best_local * 1e-6;
        const double remote = static_cast<double>(rays.size()) / best_remote * 1e-6;
        std::printf(
            "{\"measure\":\"throughput\",\"rays\":\"%s\",\"count\":%zu,\"threads\":%u,\"in_process_mrays\":%.2f,"
            "\"http_mrays\":%.2f,\"ratio\":%.3f,\"in_process_ms\":%.1f,\"http_ms\":%.1f,\"server_side_ms\":%.1f,"
            "\"same_hits\":%s}\n",
            std::string(kdrt::ray_kind_name(kind)).c_str(), rays.size(), threads, local, remote, remote / local,
            best_local * 1e3, best_remote * 1e3, server.fastest_logged_ms(rays.size()), same ? "true" : "false");
        std::fflush(stdout);
    }

    // Latency of small requests over one keep-alive connection.
    for (const size_t count : {size_t{1}, size_t{1000}}) {
        const std::vector<kdrt::Ray> rays =
            kdrt::generate_rays(tree, {.kind = kdrt::RayKind::kPrimary, .res = 64, .seed = 3});
        const std::string body =
            as_string(kdrt::proto::encode_rays(std::span(rays).first(std::min(count, rays.size())), false));
        std::vector<double> us;
        for (int i = 0; i < latency_requests + 50; ++i) {
            std::string answer;
            const double s = trace_remote(*cli, path, body, 16 + 16 * count, answer);
            if (i >= 50) us.push_back(s * 1e6);  // the first 50 warm up
        }
        std::printf("{\"measure\":\"latency\",\"rays\":%zu,\"requests\":%d,\"p50_us\":%.1f,\"p99_us\":%.1f}\n", count,
                    latency_requests, percentile(us, 0.5), percentile(us, 0.99));
        std::fflush(stdout);
    }

    // Render latency: 1024^2 eyelight PNG.
    std::vector<double> ms, render_ms;
    const std::string request =
        "{\"mesh\":\"" + bunny_id + "\",\"width\":1024,\"height\":1024,\"shading\":\"eyelight\"}";
    for (int i = 0; i < reps + 1; ++i) {
        const auto start = Clock::now();
        auto res = cli->Post("/v1/render", request, "application/json");
        const double s = seconds_since(start);
        if (!res || res->status != 200) {
            std::fprintf(stderr, "render failed\n");
            return 1;
        }
        if (i == 0) continue;  // warm-up
        ms.push_back(s * 1e3);
        render_ms.push_back(std::stod(res->get_header_value("X-Render-Ms")));
    }
    std::printf(
        "{\"measure\":\"render\",\"size\":1024,\"shading\":\"eyelight\",\"format\":\"png\",\"p50_ms\":%.1f,"
        "\"render_only_p50_ms\":%.1f}\n",
        percentile(ms, 0.5), percentile(render_ms, 0.5));
    return 0;
}
