// kdrt-server-bench: the server's performance numbers (issue "kdrt-server", Performance).
// Starts the real kdrt-server on an ephemeral loopback port and measures, in one run:
//   - upload-to-ready of the bunny and of a 1M-triangle mesh (POST until the 201 arrives),
//   - 1M-ray primary and diffuse batches over loopback HTTP (KDRR -> KDRH) against the same rays
//     traced in process with the same thread count, alternating, as Mrays/s (median of --reps)
//     and their ratio,
//   - 1-ray and 1k-ray intersect latency over one keep-alive connection (p50, p99),
//   - 1024^2 eyelight render latency over HTTP (p50), at the default and at explicit PNG
//     compression levels, with the server's render and encode times.
// Intersect requests go through a minimal HTTP/1.1 keep-alive client on a plain socket (large
// reads straight into a reused buffer), so the numbers are the server's, not a client
// library's; "httplib_client_mrays" is the same batch through cpp-httplib's client, and
// "client_mrays" through kdrt::Client (its default chunking over parallel connections), with
// "client_ratio" = client_mrays / http_mrays. Prints one JSON object per measurement;
// "server_side_ms" is the server's own time for the request (its access log: headers read to
// response written). Not a ctest test (a benchmark asserts nothing).
//
//   kdrt-server-bench [--threads N] [--reps R] [--latency-requests K] [--server PATH]
//                     [--only upload,throughput,latency,render]

#include <fcntl.h>
#include <httplib.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <tbb/task_arena.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "kdrt/client/client.h"
#include "kdrt/kdtree.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/raygen.h"
#include "kdrt/trace.h"

namespace {

using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;

double seconds_since(Clock::time_point start) {
    return std::chrono::duration<double>(Clock::now() - start).count();
}

std::string as_string(const std::vector<std::byte>& bytes) {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

double median(std::vector<double> values) {
    std::sort(values.begin(), values.end());
    const size_t n = values.size();
    return n % 2 ? values[n / 2] : 0.5 * (values[n / 2 - 1] + values[n / 2]);
}

double percentile(std::vector<double> values, double p) {
    std::sort(values.begin(), values.end());
    const size_t index =
        std::min(values.size() - 1, static_cast<size_t>(p * static_cast<double>(values.size())));
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
            const uint32_t c = ((i + 1) % rings) * sides + (j + 1) % sides,
                           d = i * sides + (j + 1) % sides;
            m.indices.insert(m.indices.end(), {a, b, c, a, c, d});
        }
    }
    return m;
}

/// The server's pid while it runs, so an early exit (a failed request) does not leave it behind.
pid_t g_server_pid = -1;
void stop_server_at_exit() {
    if (g_server_pid > 0) ::kill(g_server_pid, SIGTERM);
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
            ::execl(binary.c_str(), binary.c_str(), "--listen", "127.0.0.1:0", "--port-file",
                    port_file.c_str(), "--cache-dir", cache.c_str(), "--threads", t.c_str(),
                    "--max-inflight", "1000", static_cast<char*>(nullptr));
            ::_exit(127);
        }
        g_server_pid = pid;
        std::atexit(stop_server_at_exit);
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
    /// Size of the server's log so far (to read only what follows with logged_ms).
    uint64_t log_size() const { return fs::file_size(dir / "server.log"); }
    /// The server's own times (from its access log, after byte `from`) of intersect requests
    /// with `rays` rays.
    std::vector<double> logged_ms(uint64_t from, size_t rays) const {
        std::ifstream in(dir / "server.log");
        in.seekg(static_cast<std::streamoff>(from));
        std::string line;
        std::vector<double> out;
        const std::string key = "rays=" + std::to_string(rays) + " ms=";
        while (std::getline(in, line)) {
            const size_t at = line.find(key);
            if (at != std::string::npos && line.find("/intersect") != std::string::npos)
                out.push_back(std::stod(line.substr(at + key.size())));
        }
        return out;
    }

    ~Server() {
        ::kill(pid, SIGTERM);
        int status = 0;
        ::waitpid(pid, &status, 0);
        g_server_pid = -1;
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
    const std::string body =
        as_string(kdrt::proto::write_mesh(mesh, kdrt::proto::MeshFormat::kRaw));
    const auto start = Clock::now();
    auto res = cli.Post("/v1/meshes", body, "application/x-kdrt-mesh");
    const double s = seconds_since(start);
    if (!res || (res->status != 201 && res->status != 200)) {
        std::fprintf(stderr, "upload failed: %d %s\n", res ? res->status : -1,
                     res ? res->body.c_str() : "");
        std::exit(1);
    }
    return {s, kdrt::proto::mesh_id(mesh)};
}

/// A minimal HTTP/1.1 client on one keep-alive loopback connection: sends a POST with
/// Content-Length and reads a Content-Length response straight into a reused buffer with large
/// reads. Enough for the server's own answers (no chunked responses, no redirects).
class RawClient {
public:
    explicit RawClient(int port) : port_(port) { connect(); }
    RawClient(const RawClient&) = delete;
    RawClient& operator=(const RawClient&) = delete;
    ~RawClient() { ::close(fd_); }

    void connect() {
        if (fd_ >= 0) ::close(fd_);
        const int port = port_;
        fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
        sockaddr_in addr{};
        addr.sin_family = AF_INET;
        addr.sin_port = htons(static_cast<uint16_t>(port));
        addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        const int one = 1;
        ::setsockopt(fd_, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
        if (fd_ < 0 || ::connect(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
            std::perror("kdrt-server-bench: connect");
            std::exit(1);
        }
    }

    /// POSTs `body`; returns the status and leaves the response body in `answer`.
    int post(const std::string& path, const char* type, std::string_view body,
             std::vector<char>& answer) {
        // An idle connection the server closed (keep_alive_timeout_s) reads as EOF: reconnect.
        pollfd idle{fd_, POLLIN | POLLRDHUP, 0};
        if (::poll(&idle, 1, 0) > 0) connect();
        const std::string head = "POST " + path +
                                 " HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: " + type +
                                 "\r\nContent-Length: " + std::to_string(body.size()) + "\r\n\r\n";
        send_all(head.data(), head.size(), body.empty() ? 0 : MSG_MORE);
        send_all(body.data(), body.size(), 0);
        // Headers: read until the blank line; whatever follows it is the start of the body.
        std::string buffered;
        size_t end = std::string::npos;
        while ((end = buffered.find("\r\n\r\n")) == std::string::npos) {
            char chunk[16384];
            const ssize_t n = ::recv(fd_, chunk, sizeof chunk, 0);
            if (n <= 0) fail("connection closed while reading the response headers");
            buffered.append(chunk, static_cast<size_t>(n));
        }
        const int status = std::atoi(buffered.c_str() + buffered.find(' ') + 1);
        std::string lower = buffered.substr(0, end);
        std::transform(lower.begin(), lower.end(), lower.begin(),
                       [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
        close_after_ = lower.find("\r\nconnection: close") != std::string::npos;
        const size_t cl = lower.find("\r\ncontent-length:");
        if (cl == std::string::npos) fail("response without Content-Length");
        const size_t length = std::stoull(lower.substr(cl + 17));
        answer.resize(length);
        size_t got = std::min(length, buffered.size() - (end + 4));
        std::memcpy(answer.data(), buffered.data() + end + 4, got);
        while (got < length) {
            const ssize_t n = ::recv(fd_, answer.data() + got, length - got, 0);
            if (n <= 0) fail("connection closed while reading the response body");
            got += static_cast<size_t>(n);
        }
        if (close_after_) connect();  // keep_alive_max_requests reached: a new connection
        return status;
    }

private:
    [[noreturn]] static void fail(const char* why) {
        std::fprintf(stderr, "kdrt-server-bench: %s\n", why);
        std::exit(1);
    }
    void send_all(const char* data, size_t size, int flags) {
        while (size > 0) {
            const ssize_t n = ::send(fd_, data, size, flags | MSG_NOSIGNAL);
            if (n < 0 && errno == EINTR) continue;
            if (n <= 0) fail("send failed");
            data += n;
            size -= static_cast<size_t>(n);
        }
    }
    int port_;
    int fd_ = -1;
    bool close_after_ = false;
};

/// One intersect POST through the raw client; returns seconds.
double trace_raw(RawClient& cli, const std::string& path, std::string_view body,
                 std::vector<char>& answer) {
    const auto start = Clock::now();
    const int status = cli.post(path, "application/x-kdrt-rays", body, answer);
    const double s = seconds_since(start);
    if (status != 200) {
        std::fprintf(stderr, "intersect failed: %d %.*s\n", status,
                     static_cast<int>(std::min<size_t>(answer.size(), 300)), answer.data());
        std::exit(1);
    }
    return s;
}

/// One POST of a KDRR body, the KDRH answer received into a pre-sized buffer.
double trace_remote(httplib::Client& cli, const std::string& path, const std::string& body,
                    size_t answer_bytes, std::string& answer) {
    answer.clear();
    answer.reserve(answer_bytes);
    auto start = Clock::now();
    auto res = cli.Post(path, body, "application/x-kdrt-rays");
    if (!res) {
        // The keep-alive connection sat idle while the other clients were measured and the
        // server closed it just as this request went out: time a second attempt instead.
        start = Clock::now();
        res = cli.Post(path, body, "application/x-kdrt-rays");
    }
    const double s = seconds_since(start);
    if (!res || res->status != 200) {
        std::fprintf(stderr, "intersect failed: %d (%s)\n", res ? res->status : -1,
                     res ? "" : httplib::to_string(res.error()).c_str());
        std::exit(1);
    }
    answer = std::move(res->body);
    return s;
}

/// `count` rays of `kind` for the bunny's tree: the res x res set of the kind, res grown until
/// it has at least `count` rays (diffuse rays exist only where primary rays hit), then cut.
std::vector<kdrt::Ray> ray_set(tbb::task_arena& arena, const kdrt::KdTree& tree, kdrt::RayKind kind,
                               size_t count) {
    for (uint32_t res = 1024;; res = res * 5 / 4) {
        std::vector<kdrt::Ray> rays = arena.execute(
            [&] { return kdrt::generate_rays(tree, {.kind = kind, .res = res, .seed = 1}); });
        if (rays.size() >= count) {
            rays.resize(count);
            return rays;
        }
    }
}

bool wanted(const std::string& only, const char* part) {
    if (only.empty()) return true;
    return ("," + only + ",").find("," + std::string(part) + ",") != std::string::npos;
}

}  // namespace

int main(int argc, char** argv) {
    unsigned threads = std::max(1u, std::thread::hardware_concurrency());
    int reps = 7;
    int latency_requests = 2000;
    std::string binary = KDRT_SERVER_BINARY, only;
    for (int i = 1; i + 1 < argc; i += 2) {
        const std::string flag = argv[i];
        if (flag == "--threads")
            threads = static_cast<unsigned>(std::stoul(argv[i + 1]));
        else if (flag == "--reps")
            reps = std::max(1, std::stoi(argv[i + 1]));
        else if (flag == "--latency-requests")
            latency_requests = std::max(1, std::stoi(argv[i + 1]));
        else if (flag == "--server")
            binary = argv[i + 1];
        else if (flag == "--only")
            only = argv[i + 1];
        else {
            std::fprintf(stderr,
                         "usage: kdrt-server-bench [--threads N] [--reps R] [--latency-requests K] "
                         "[--server PATH]\n"
                         "                         [--only upload,throughput,latency,render]\n");
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
    if (wanted(only, "upload")) {
        std::printf(
            "{\"measure\":\"upload_to_ready\",\"mesh\":\"bunny\",\"triangles\":%zu,\"ms\":%.1f}\n",
            bunny->triangle_count(), bunny_s * 1e3);
        const kdrt::Mesh big = torus(1000, 500);
        const auto [big_s, big_id] = upload(*cli, big);
        std::printf(
            "{\"measure\":\"upload_to_ready\",\"mesh\":\"torus\",\"triangles\":%zu,\"ms\":%.1f}\n",
            big.triangle_count(), big_s * 1e3);
        cli->Delete("/v1/meshes/" + big_id);
        std::fflush(stdout);
    }

    tbb::task_arena arena(static_cast<int>(threads));
    const kdrt::KdTree tree = arena.execute([&] { return kdrt::build_kdtree(*bunny); });
    const std::string path = "/v1/meshes/" + bunny_id + "/intersect";
    RawClient raw(server.port);
    kdrt::Client kdrt_client("http://127.0.0.1:" + std::to_string(server.port));

    // Throughput: the same 1M rays in process and over HTTP, alternating; medians of `reps`.
    if (wanted(only, "throughput")) {
        constexpr size_t kRays = size_t{1} << 20;
        for (const kdrt::RayKind kind : {kdrt::RayKind::kPrimary, kdrt::RayKind::kDiffuse}) {
            const std::vector<kdrt::Ray> rays = ray_set(arena, tree, kind, kRays);
            const std::string body = as_string(kdrt::proto::encode_rays(rays, false));
            std::vector<kdrt::Hit> hits(rays.size());
            std::vector<char> answer;
            std::string httplib_answer;
            trace_raw(raw, path, body, answer);  // warm-up: the server's buffers, the page cache
            const uint64_t log_from = server.log_size();
            std::vector<kdrt::Hit> client_hits;
            std::vector<double> local, remote, via_httplib, via_client;
            for (int r = 0; r < reps; ++r) {
                const auto start = Clock::now();
                arena.execute([&] { kdrt::intersect(tree, rays, hits); });
                local.push_back(seconds_since(start));
                remote.push_back(trace_raw(raw, path, body, answer));
                via_httplib.push_back(
                    trace_remote(*cli, path, body, 16 + 16 * rays.size(), httplib_answer));
                const auto client_start = Clock::now();
                auto answered = kdrt_client.intersect(bunny_id, rays);
                via_client.push_back(seconds_since(client_start));
                if (!answered) {
                    std::fprintf(stderr, "kdrt::Client intersect failed: %s\n",
                                 answered.error().to_string().c_str());
                    return 1;
                }
                client_hits = std::move(*answered);
            }
            // The server logs each request after answering it; in order: raw, httplib, raw, ...
            // (kdrt::Client's chunks have another ray count).
            std::vector<double> raw_logged;
            const std::vector<double> logged = server.logged_ms(log_from, rays.size());
            for (size_t i = 0; i < logged.size(); i += 2) raw_logged.push_back(logged[i]);
            if (raw_logged.empty()) raw_logged.push_back(-1);
            const std::string expected = as_string(kdrt::proto::encode_hits(hits));
            const bool same = std::string_view(answer.data(), answer.size()) == expected &&
                              httplib_answer == expected &&
                              as_string(kdrt::proto::encode_hits(client_hits)) == expected;
            const double n = static_cast<double>(rays.size()) * 1e-6;
            const double local_mrays = n / median(local), remote_mrays = n / median(remote);
            std::printf(
                "{\"measure\":\"throughput\",\"rays\":\"%s\",\"count\":%zu,\"threads\":%u,\"reps\":"
                "%d,"
                "\"in_process_mrays\":%.2f,\"http_mrays\":%.2f,\"ratio\":%.3f,\"httplib_client_"
                "mrays\":%.2f,"
                "\"client_mrays\":%.2f,\"client_ratio\":%.3f,"
                "\"in_process_ms\":%.1f,\"http_ms\":%.1f,\"server_side_ms\":%.1f,\"same_hits\":%s}"
                "\n",
                std::string(kdrt::ray_kind_name(kind)).c_str(), rays.size(), threads, reps,
                local_mrays, remote_mrays, remote_mrays / local_mrays, n / median(via_httplib),
                n / median(via_client), n / median(via_client) / remote_mrays, median(local) * 1e3,
                median(remote) * 1e3, median(raw_logged), same ? "true" : "false");
            std::fflush(stdout);
        }
    }

    // Latency of small requests over one keep-alive connection.
    if (wanted(only, "latency")) {
        const std::vector<kdrt::Ray> rays =
            kdrt::generate_rays(tree, {.kind = kdrt::RayKind::kPrimary, .res = 64, .seed = 3});
        for (const size_t count : {size_t{1}, size_t{1000}}) {
            const std::string body = as_string(kdrt::proto::encode_rays(
                std::span(rays).first(std::min(count, rays.size())), false));
            std::vector<double> us;
            std::vector<char> answer;
            for (int i = 0; i < latency_requests + 50; ++i) {
                const double s = trace_raw(raw, path, body, answer);
                if (i >= 50) us.push_back(s * 1e6);  // the first 50 warm up
            }
            std::printf(
                "{\"measure\":\"latency\",\"rays\":%zu,\"requests\":%d,\"p50_us\":%.1f,\"p99_us\":%"
                ".1f}\n",
                count, latency_requests, percentile(us, 0.5), percentile(us, 0.99));
            std::fflush(stdout);
        }
    }

    // Render latency: 1024^2 eyelight PNG, at the server's default compression and at 0, 6, 9.
    if (wanted(only, "render")) {
        for (const int level : {-1, 0, 6, 9}) {
            std::string request = "{\"mesh\":\"" + bunny_id +
                                  "\",\"width\":1024,\"height\":1024,\"shading\":\"eyelight\"";
            if (level >= 0) request += ",\"compression\":" + std::to_string(level);
            request += "}";
            std::vector<double> ms, render_ms, encode_ms;
            size_t bytes = 0;
            for (int i = 0; i < reps + 1; ++i) {
                const auto start = Clock::now();
                auto res = cli->Post("/v1/render", request, "application/json");
                const double s = seconds_since(start);
                if (!res || res->status != 200) {
                    std::fprintf(stderr, "render failed: %d %s\n", res ? res->status : -1,
                                 res ? res->body.c_str() : "");
                    return 1;
                }
                if (i == 0) continue;  // warm-up
                ms.push_back(s * 1e3);
                render_ms.push_back(std::stod(res->get_header_value("X-Render-Ms")));
                encode_ms.push_back(res->has_header("X-Encode-Ms")
                                        ? std::stod(res->get_header_value("X-Encode-Ms"))
                                        : -1);
                bytes = res->body.size();
            }
            std::printf(
                "{\"measure\":\"render\",\"size\":1024,\"shading\":\"eyelight\",\"format\":\"png\","
                "\"compression\":%s,"
                "\"p50_ms\":%.1f,\"render_only_p50_ms\":%.1f,\"encode_p50_ms\":%.1f,\"bytes\":%zu}"
                "\n",
                level < 0 ? "\"default\"" : std::to_string(level).c_str(), median(ms),
                median(render_ms), median(encode_ms), bytes);
            std::fflush(stdout);
        }
    }
    return 0;
}
