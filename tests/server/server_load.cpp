// kdrt-server-load: load against a real kdrt-server (issue "Service hardening", Load and
// Starvation). Starts the server on an ephemeral loopback port (or uses --port/--pid of one that
// runs) and runs one of:
//
//   starve  --slow-head N --slow-body N --idle N --probes N
//           Opens N slow-header clients (a request head trickled one byte a second), N
//           slow-body clients (a 1000-byte render body trickled one byte a second) and N idle
//           keep-alive connections (one request answered, then silence), then sends --probes
//           fresh GET /healthz requests (each on a new connection) and prints their latency
//           (p50, p99, max), failures, how many slow clients were cut with 408 and when, and the
//           server's RSS before and after.
//   mixed   --connections N --seconds S --max-requests N
//           N client connections, each a thread issuing requests back to back for S seconds or
//           until --max-requests in all: uploads of small meshes, 1k-ray and 1M-ray KDRR
//           batches, 64x64 renders, mesh listings, mesh summaries, /metrics. Prints requests/s,
//           p50/p99 per kind, every status count per kind, unexpected 5xx (any 5xx but a 503
//           with Retry-After), and the server's RSS (VmRSS, VmHWM) before and after.
//
// One JSON object per line on stdout. Not a ctest test (a load run asserts nothing); bounded in
// time and count so it can be rerun: see tests/README.md.
//
//   kdrt-server-load starve|mixed [--server PATH] [--port P --pid PID] [options above]
//                    [--server-arg ARG]...   (extra flags for the started server)

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "kdrt/proto/json_api.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/ray_batch_codec.h"
#include "test_util.h"

namespace {

using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;

double ms_since(Clock::time_point t) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t).count();
}

double percentile(std::vector<double> v, double p) {
    if (v.empty()) return 0;
    std::sort(v.begin(), v.end());
    const size_t i = std::min(v.size() - 1, static_cast<size_t>(p * static_cast<double>(v.size())));
    return v[i];
}

std::string as_string(const std::vector<std::byte>& bytes) {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

/// VmRSS and VmHWM of `pid` in MiB.
std::pair<double, double> rss_mib(pid_t pid) {
    std::ifstream in("/proc/" + std::to_string(pid) + "/status");
    std::string line;
    double rss = 0, hwm = 0;
    while (std::getline(in, line)) {
        if (line.rfind("VmRSS:", 0) == 0) rss = std::stod(line.substr(6)) / 1024;
        if (line.rfind("VmHWM:", 0) == 0) hwm = std::stod(line.substr(6)) / 1024;
    }
    return {rss, hwm};
}

int connect_to(int port) {
    const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    if (fd < 0) return -1;
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<uint16_t>(port));
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
        ::close(fd);
        return -1;
    }
    const int one = 1;
    ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    return fd;
}

bool send_all(int fd, std::string_view data) {
    while (!data.empty()) {
        const ssize_t n = ::send(fd, data.data(), data.size(), MSG_NOSIGNAL);
        if (n <= 0) return false;
        data.remove_prefix(static_cast<size_t>(n));
    }
    return true;
}

/// {"200":12,"503":3}
std::string status_json(const std::map<int, size_t>& counts) {
    std::string out = "{";
    for (const auto& [status, count] : counts) {
        if (out.size() > 1) out.push_back(',');
        out.append("\"").append(std::to_string(status)).append("\":").append(std::to_string(count));
    }
    out.push_back('}');
    return out;
}

struct Reply {
    int status = 0;  ///< 0: no reply (connection failed or timed out)
    std::string body;
    bool retry_after = false;
};

/// A minimal HTTP/1.1 keep-alive client on a blocking socket (reconnects after a close).
class Connection {
public:
    explicit Connection(int port) : port_(port) {}
    ~Connection() { drop(); }
    Connection(const Connection&) = delete;
    Connection& operator=(const Connection&) = delete;

    Reply request(const std::string& method, const std::string& path,
                  const std::string& content_type = {}, const std::string& body = {}) {
        if (fd_ < 0 && !open()) return {};
        std::string head = method + " " + path + " HTTP/1.1\r\nHost: load\r\n";
        if (!content_type.empty()) head += "Content-Type: " + content_type + "\r\n";
        if (method == "POST") head += "Content-Length: " + std::to_string(body.size()) + "\r\n";
        head += "\r\n";
        if (!send_all(fd_, head) || !send_all(fd_, body)) return fail();
        return read_reply();
    }

private:
    bool open() {
        fd_ = connect_to(port_);
        if (fd_ < 0) return false;
        timeval tv{120, 0};
        ::setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
        buffer_.clear();
        return true;
    }
    void drop() {
        if (fd_ >= 0) ::close(fd_);
        fd_ = -1;
    }
    Reply fail() {
        drop();
        return {};
    }
    bool fill() {
        char chunk[65536];
        const ssize_t n = ::recv(fd_, chunk, sizeof chunk, 0);
        if (n <= 0) return false;
        buffer_.append(chunk, static_cast<size_t>(n));
        return true;
    }
    Reply read_reply() {
        size_t end = 0;
        while ((end = buffer_.find("\r\n\r\n")) == std::string::npos)
            if (!fill()) return fail();
        const std::string head = buffer_.substr(0, end + 2);
        buffer_.erase(0, end + 4);
        Reply r;
        if (head.size() < 12) return fail();
        r.status = std::atoi(head.c_str() + 9);
        std::string lower = head;
        std::transform(lower.begin(), lower.end(), lower.begin(),
                       [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
        r.retry_after = lower.find("\r\nretry-after:") != std::string::npos;
        const bool close = lower.find("\r\nconnection: close") != std::string::npos;
        const size_t cl = lower.find("\r\ncontent-length:");
        if (cl != std::string::npos) {
            const size_t length = std::stoull(head.substr(cl + 17));
            while (buffer_.size() < length)
                if (!fill()) return fail();
            r.body = buffer_.substr(0, length);
            buffer_.erase(0, length);
        } else if (lower.find("chunked") != std::string::npos) {
            for (;;) {
                size_t line_end = 0;
                while ((line_end = buffer_.find("\r\n")) == std::string::npos)
                    if (!fill()) return fail();
                const size_t size = std::stoull(buffer_.substr(0, line_end), nullptr, 16);
                while (buffer_.size() < line_end + 2 + size + 2)
                    if (!fill()) return fail();
                r.body.append(buffer_, line_end + 2, size);
                buffer_.erase(0, line_end + 2 + size + 2);
                if (size == 0) break;
            }
        }
        if (close) drop();
        return r;
    }

    int port_;
    int fd_ = -1;
    std::string buffer_;
};

pid_t g_server_pid = -1;
void stop_server_at_exit() {
    if (g_server_pid > 0) ::kill(g_server_pid, SIGTERM);
}

/// The server under load: started here, or given with --port and --pid.
struct Server {
    pid_t pid = -1;
    int port = 0;
    bool owned = false;
    fs::path dir;

    Server(const std::string& binary, const std::vector<std::string>& extra) {
        owned = true;
        dir = fs::temp_directory_path() / ("kdrt-server-load-" + std::to_string(::getpid()));
        fs::remove_all(dir);
        fs::create_directories(dir);
        const std::string port_file = (dir / "port").string();
        std::vector<std::string> args = {binary,
                                         "--listen",
                                         "127.0.0.1:0",
                                         "--port-file",
                                         port_file,
                                         "--cache-dir",
                                         (dir / "cache").string(),
                                         "--log-level",
                                         "warn"};
        args.insert(args.end(), extra.begin(), extra.end());
        pid = ::fork();
        if (pid == 0) {
            const int log_fd =
                ::open((dir / "server.log").c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
            ::dup2(log_fd, 2);
            std::vector<char*> argv;
            argv.reserve(args.size() + 1);
            for (std::string& a : args) argv.push_back(a.data());
            argv.push_back(nullptr);
            ::execv(binary.c_str(), argv.data());
            ::_exit(127);
        }
        g_server_pid = pid;
        std::atexit(stop_server_at_exit);
        for (int i = 0; i < 6000 && port == 0; ++i) {
            std::ifstream in(port_file);
            if (!(in >> port)) std::this_thread::sleep_for(std::chrono::milliseconds(10));
        }
        wait_ready();
    }
    Server(int p, pid_t id) : pid(id), port(p) { wait_ready(); }

    void wait_ready() const {
        Connection c(port);
        for (int i = 0; i < 6000; ++i) {
            if (c.request("GET", "/readyz").status == 200) return;
            std::this_thread::sleep_for(std::chrono::milliseconds(10));
        }
        std::fprintf(stderr, "kdrt-server-load: the server is not ready\n");
        std::exit(1);
    }

    ~Server() {
        if (!owned) return;
        ::kill(pid, SIGTERM);
        int status = 0;
        ::waitpid(pid, &status, 0);
        g_server_pid = -1;
        fs::remove_all(dir);
    }
};

struct Options {
    std::string mode;
    std::string server;
    int port = 0;
    pid_t pid = -1;
    std::vector<std::string> server_args;
    size_t slow_head = 200, slow_body = 200, idle = 1000, probes = 500;
    size_t connections = 64, max_requests = 200000;
    double seconds = 60;
};

// ---- starve ----------------------------------------------------------------------------------

int run_starve(const Server& server, const Options& o) {
    const auto [rss_before, hwm_before] = rss_mib(server.pid);
    struct Slow {
        int fd;
        Clock::time_point opened;
        bool body;
        int status = 0;  ///< of the reply that cut it (0: none yet)
        double cut_ms = 0;
    };
    std::vector<Slow> slow;
    std::vector<int> idle;
    size_t failed_opens = 0;
    for (size_t i = 0; i < o.idle; ++i) {
        const int fd = connect_to(server.port);
        if (fd < 0 || !send_all(fd, "GET /healthz HTTP/1.1\r\nHost: load\r\n\r\n")) {
            ++failed_opens;
            continue;
        }
        idle.push_back(fd);
    }
    size_t idle_answered = 0;
    for (const int fd : idle) {
        pollfd p{fd, POLLIN, 0};
        char buf[2048];
        if (::poll(&p, 1, 30000) > 0 && ::recv(fd, buf, sizeof buf, 0) > 0) ++idle_answered;
    }
    for (size_t i = 0; i < o.slow_head + o.slow_body; ++i) {
        const bool body = i >= o.slow_head;
        const int fd = connect_to(server.port);
        if (fd < 0) {
            ++failed_opens;
            continue;
        }
        const std::string start = body ? "POST /v1/render HTTP/1.1\r\nHost: load\r\nContent-Type: "
                                         "application/json\r\nContent-Length: 1000\r\n\r\n{"
                                       : "GET /healthz HTTP/1.1\r\nHost: load\r\nX-Slow: ";
        send_all(fd, start);
        slow.push_back({fd, Clock::now(), body});
    }
    std::atomic<bool> stop{false};
    std::thread trickle([&] {
        while (!stop) {
            for (Slow& s : slow) {
                if (s.status != 0) continue;
                pollfd p{s.fd, POLLIN, 0};
                if (::poll(&p, 1, 0) > 0) {
                    char buf[4096];
                    const ssize_t n = ::recv(s.fd, buf, sizeof buf, MSG_DONTWAIT);
                    s.status = n >= 12 ? std::atoi(buf + 9) : -1;
                    s.cut_ms = ms_since(s.opened);
                    continue;
                }
                ::send(s.fd, "a", 1, MSG_NOSIGNAL | MSG_DONTWAIT);
            }
            std::this_thread::sleep_for(std::chrono::seconds(1));
        }
    });
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    std::vector<double> latency;
    size_t probe_failures = 0;
    const auto probe_start = Clock::now();
    for (size_t i = 0; i < o.probes; ++i) {
        const auto t = Clock::now();
        Connection c(server.port);
        const Reply r = c.request("GET", "/healthz");
        if (r.status == 200)
            latency.push_back(ms_since(t));
        else
            ++probe_failures;
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    const double probe_s = ms_since(probe_start) / 1e3;
    const auto [rss_mid, hwm_mid] = rss_mib(server.pid);
    // Wait for the deadlines to cut the slow clients (bounded: 2 minutes).
    const auto wait_start = Clock::now();
    for (;;) {
        const bool all_cut =
            std::all_of(slow.begin(), slow.end(), [](const Slow& s) { return s.status != 0; });
        if (all_cut || ms_since(wait_start) > 120000) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(200));
    }
    stop = true;
    trickle.join();
    std::map<int, size_t> head_status, body_status;
    double head_cut_max = 0, body_cut_max = 0;
    for (const Slow& s : slow) {
        (s.body ? body_status : head_status)[s.status]++;
        double& m = s.body ? body_cut_max : head_cut_max;
        m = std::max(m, s.cut_ms);
        ::close(s.fd);
    }
    for (const int fd : idle) ::close(fd);
    const auto [rss_after, hwm_after] = rss_mib(server.pid);
    std::printf(
        "{\"mode\":\"starve\",\"slow_head\":%zu,\"slow_body\":%zu,\"idle\":%zu,"
        "\"idle_answered\":%zu,\"failed_opens\":%zu,\"probes\":%zu,\"probe_failures\":%zu,"
        "\"probe_seconds\":%.1f,\"healthz_p50_ms\":%.2f,\"healthz_p99_ms\":%.2f,"
        "\"healthz_max_ms\":%.2f,\"slow_head_status\":%s,\"slow_head_cut_max_ms\":%.0f,"
        "\"slow_body_status\":%s,\"slow_body_cut_max_ms\":%.0f,\"rss_before_mib\":%.1f,"
        "\"rss_loaded_mib\":%.1f,\"rss_after_mib\":%.1f,\"hwm_mib\":%.1f}\n",
        o.slow_head, o.slow_body, o.idle, idle_answered, failed_opens, o.probes, probe_failures,
        probe_s, percentile(latency, 0.5), percentile(latency, 0.99), percentile(latency, 1.0),
        status_json(head_status).c_str(), head_cut_max, status_json(body_status).c_str(),
        body_cut_max, rss_before, rss_mid, rss_after, hwm_after);
    (void)hwm_before;
    (void)hwm_mid;
    return probe_failures == 0 ? 0 : 1;
}

// ---- mixed -----------------------------------------------------------------------------------

enum Kind { kUpload, kBatch1k, kBatch1m, kRender, kList, kSummary, kMetrics, kKinds };
constexpr const char* kKindNames[kKinds] = {"upload", "batch_1k", "batch_1m", "render_64",
                                            "list",   "summary",  "metrics"};

struct KindStats {
    std::vector<double> ms;
    std::map<int, size_t> status;
    size_t unexpected_5xx = 0;
};

int run_mixed(const Server& server, const Options& o) {
    using kdrt::test::Rng;
    Connection setup(server.port);
    Rng rng(20261202);
    const kdrt::Mesh base = kdrt::test::random_soup(rng, 20000);
    kdrt::proto::MeshWriteOptions write;
    const std::string base_body =
        as_string(kdrt::proto::write_mesh(base, kdrt::proto::MeshFormat::kRaw, write));
    const Reply uploaded =
        setup.request("POST", "/v1/meshes", "application/x-kdrt-mesh", base_body);
    auto summary = kdrt::proto::decode_mesh_summary(uploaded.body);
    if (!summary) {
        std::fprintf(stderr, "kdrt-server-load: upload failed: %d %s\n", uploaded.status,
                     uploaded.body.c_str());
        return 1;
    }
    const std::string id = summary->id;
    const std::string batch_1k =
        as_string(kdrt::proto::encode_rays(kdrt::test::rays_towards_unit_cube(1000, 1), false));
    const std::string batch_1m =
        as_string(kdrt::proto::encode_rays(kdrt::test::rays_towards_unit_cube(1u << 20, 2), false));
    const std::string render =
        "{\"mesh\":\"" + id + "\",\"width\":64,\"height\":64,\"shading\":\"eyelight\"}";
    const auto [rss_before, hwm_before] = rss_mib(server.pid);

    std::mutex mutex;
    std::vector<KindStats> stats(kKinds);
    std::atomic<size_t> issued{0};
    std::atomic<int> big_in_flight{0};
    const auto start = Clock::now();
    const auto end = start + std::chrono::duration<double>(o.seconds);
    std::vector<std::thread> threads;
    threads.reserve(o.connections);
    for (size_t t = 0; t < o.connections; ++t) {
        threads.emplace_back([&, t] {
            Connection c(server.port);
            Rng pick(1000 + t);
            uint64_t upload_seed = (t + 1) * 1000000;
            std::vector<KindStats> local(kKinds);
            while (Clock::now() < end && issued.fetch_add(1) < o.max_requests) {
                const uint32_t roll = pick.below(100);
                Kind kind = roll < 5    ? kUpload
                            : roll < 45 ? kBatch1k
                            : roll < 48 ? kBatch1m
                            : roll < 60 ? kRender
                            : roll < 75 ? kList
                            : roll < 90 ? kSummary
                                        : kMetrics;
                // At most two 1M-ray batches at once (each is a 32 MiB body and 2 cores' work).
                if (kind == kBatch1m && big_in_flight.fetch_add(1) >= 2) {
                    big_in_flight.fetch_sub(1);
                    kind = kBatch1k;
                }
                const auto t0 = Clock::now();
                Reply r;
                switch (kind) {
                    case kUpload: {
                        Rng mesh_rng(++upload_seed);
                        const kdrt::Mesh m = kdrt::test::random_soup(mesh_rng, 500);
                        r = c.request("POST", "/v1/meshes", "application/x-kdrt-mesh",
                                      as_string(kdrt::proto::write_mesh(
                                          m, kdrt::proto::MeshFormat::kRaw, write)));
                        break;
                    }
                    case kBatch1k:
                        r = c.request("POST", "/v1/meshes/" + id + "/intersect",
                                      "application/x-kdrt-rays", batch_1k);
                        break;
                    case kBatch1m:
                        r = c.request("POST", "/v1/meshes/" + id + "/intersect",
                                      "application/x-kdrt-rays", batch_1m);
                        big_in_flight.fetch_sub(1);
                        break;
                    case kRender:
                        r = c.request("POST", "/v1/render", "application/json", render);
                        break;
                    case kList:
                        r = c.request("GET", "/v1/meshes");
                        break;
                    case kSummary:
                        r = c.request("GET", "/v1/meshes/" + id);
                        break;
                    case kMetrics:
                        r = c.request("GET", "/metrics");
                        break;
                    case kKinds:
                        break;
                }
                KindStats& s = local[kind];
                s.ms.push_back(ms_since(t0));
                s.status[r.status]++;
                if (r.status >= 500 && !(r.status == 503 && r.retry_after)) ++s.unexpected_5xx;
                if (r.status == 0) std::this_thread::sleep_for(std::chrono::milliseconds(10));
            }
            std::lock_guard lock(mutex);
            for (int k = 0; k < kKinds; ++k) {
                stats[k].ms.insert(stats[k].ms.end(), local[k].ms.begin(), local[k].ms.end());
                for (const auto& [status, n] : local[k].status) stats[k].status[status] += n;
                stats[k].unexpected_5xx += local[k].unexpected_5xx;
            }
        });
    }
    for (std::thread& t : threads) t.join();
    const double elapsed = ms_since(start) / 1e3;
    const auto [rss_after, hwm_after] = rss_mib(server.pid);
    size_t total = 0, unexpected = 0;
    for (int k = 0; k < kKinds; ++k) {
        const KindStats& s = stats[k];
        total += s.ms.size();
        unexpected += s.unexpected_5xx;
        const std::string status = status_json(s.status);
        std::printf(
            "{\"mode\":\"mixed\",\"kind\":\"%s\",\"requests\":%zu,\"per_s\":%.1f,\"p50_ms\":%.2f,"
            "\"p99_ms\":%.2f,\"status\":%s,\"unexpected_5xx\":%zu}\n",
            kKindNames[k], s.ms.size(), static_cast<double>(s.ms.size()) / elapsed,
            percentile(s.ms, 0.5), percentile(s.ms, 0.99), status.c_str(), s.unexpected_5xx);
    }
    std::printf(
        "{\"mode\":\"mixed\",\"kind\":\"all\",\"connections\":%zu,\"seconds\":%.1f,"
        "\"requests\":%zu,\"per_s\":%.1f,\"unexpected_5xx\":%zu,\"rss_before_mib\":%.1f,"
        "\"hwm_before_mib\":%.1f,\"rss_after_mib\":%.1f,\"hwm_after_mib\":%.1f}\n",
        o.connections, elapsed, total, static_cast<double>(total) / elapsed, unexpected, rss_before,
        hwm_before, rss_after, hwm_after);
    return unexpected == 0 ? 0 : 1;
}

[[noreturn]] void usage(const char* why) {
    std::fprintf(stderr,
                 "kdrt-server-load: %s\nusage: kdrt-server-load starve|mixed [--server PATH] "
                 "[--port P --pid PID] [--server-arg ARG]... [--slow-head N] [--slow-body N] "
                 "[--idle N] [--probes N] [--connections N] [--seconds S] [--max-requests N]\n",
                 why);
    std::exit(2);
}

}  // namespace

int main(int argc, char** argv) {
    Options o;
    o.server = KDRT_SERVER_BINARY;
    if (argc < 2) usage("no mode");
    o.mode = argv[1];
    if (o.mode != "starve" && o.mode != "mixed") usage("the mode is starve or mixed");
    for (int i = 2; i < argc; ++i) {
        const std::string a = argv[i];
        if (i + 1 >= argc) usage(("no value for " + a).c_str());
        const std::string v = argv[++i];
        if (a == "--server")
            o.server = v;
        else if (a == "--port")
            o.port = std::stoi(v);
        else if (a == "--pid")
            o.pid = std::stoi(v);
        else if (a == "--server-arg")
            o.server_args.push_back(v);
        else if (a == "--slow-head")
            o.slow_head = std::stoul(v);
        else if (a == "--slow-body")
            o.slow_body = std::stoul(v);
        else if (a == "--idle")
            o.idle = std::stoul(v);
        else if (a == "--probes")
            o.probes = std::stoul(v);
        else if (a == "--connections")
            o.connections = std::stoul(v);
        else if (a == "--seconds")
            o.seconds = std::stod(v);
        else if (a == "--max-requests")
            o.max_requests = std::stoul(v);
        else
            usage(("unknown option " + a).c_str());
    }
    // This process holds every client socket: lift its open-file limit to the hard limit.
    rlimit limit{};
    if (::getrlimit(RLIMIT_NOFILE, &limit) == 0) {
        limit.rlim_cur = limit.rlim_max;
        ::setrlimit(RLIMIT_NOFILE, &limit);
    }
    ::signal(SIGPIPE, SIG_IGN);
    std::optional<Server> server;
    if (o.port > 0)
        server.emplace(o.port, o.pid);
    else
        server.emplace(o.server, o.server_args);
    return o.mode == "starve" ? run_starve(*server, o) : run_mixed(*server, o);
}
