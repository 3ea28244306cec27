// The HTTP front end in process (no server binary): what the route wrapper does when a handler
// throws. A test-only route (HttpServer::add_route_for_tests, never registered by kdrt-server)
// throws a std::exception and a non-std exception; both must become a 500 problem+json that
// names the request id, leaks nothing of the exception, closes the connection, and leaves the
// server serving.

#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <httplib.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <stdexcept>
#include <string>
#include <thread>

#include "http/http_server.h"
#include "kdrt/proto/problem.h"
#include "service.h"

namespace kdrt::server {
namespace {

namespace fs = std::filesystem;

/// A Service + HttpServer on an ephemeral loopback port, serving on a thread.
class InProcessServer {
public:
    explicit InProcessServer(const std::function<void(HttpServer&)>& add_routes,
                             const std::function<void(ServerConfig&)>& configure = {}) {
        static std::atomic<int> counter{0};
        dir_ = fs::temp_directory_path() / ("kdrt-wrapper-test-" + std::to_string(::getpid()) +
                                            "-" + std::to_string(counter++));
        fs::remove_all(dir_);
        ServerConfig config;
        config.cache_dir = (dir_ / "cache").string();
        config.threads = 1;
        config.http_threads = 2;
        if (configure) configure(config);
        service_ = std::make_unique<Service>(config);
        service_->ready = true;
        http_ = std::make_unique<HttpServer>(*service_);
        add_routes(*http_);
        auto bound = http_->bind("127.0.0.1", 0);
        EXPECT_TRUE(bound) << (bound ? "" : bound.error());
        port_ = bound ? *bound : 0;
        if (port_ > 0) serving_ = std::thread([this] { http_->serve(); });
    }
    ~InProcessServer() {
        http_->stop();
        if (serving_.joinable()) serving_.join();
        http_.reset();
        service_.reset();
        fs::remove_all(dir_);
    }
    InProcessServer(const InProcessServer&) = delete;
    InProcessServer& operator=(const InProcessServer&) = delete;

    [[nodiscard]] int port() const noexcept { return port_; }

private:
    fs::path dir_;
    std::unique_ptr<Service> service_;
    std::unique_ptr<HttpServer> http_;
    std::thread serving_;
    int port_ = 0;
};

struct NotAStdException {
    int code = 42;
};

TEST(HttpWrapper, ExceptionsFromHandlersAre500ProblemsAndTheServerGoesOn) {
    InProcessServer server([](HttpServer& http) {
        http.add_route_for_tests("/test/throw-std",
                                 [] { throw std::runtime_error("secret internal detail"); });
        http.add_route_for_tests("/test/throw-other", [] { throw NotAStdException{}; });
        http.add_route_for_tests("/test/ok", [] {});
    });
    ASSERT_GT(server.port(), 0);
    httplib::Client cli("127.0.0.1", server.port());
    cli.set_read_timeout(30, 0);
    for (const std::string path : {"/test/throw-std", "/test/throw-other"}) {
        SCOPED_TRACE(path);
        auto res = cli.Get(path);
        ASSERT_TRUE(res) << httplib::to_string(res.error());
        EXPECT_EQ(res->status, 500);
        EXPECT_EQ(res->get_header_value("Content-Type"), "application/problem+json");
        EXPECT_EQ(res->get_header_value("Connection"), "close");
        EXPECT_EQ(res->body.find("secret"), std::string::npos) << res->body;
        auto problem = proto::decode_problem(res->body);
        ASSERT_TRUE(problem) << problem.error() << ": " << res->body;
        EXPECT_EQ(problem->kind, proto::ProblemKind::kInternal);
        EXPECT_EQ(problem->instance, path);
        ASSERT_FALSE(problem->request_id.empty());
        EXPECT_NE(problem->detail.find(problem->request_id), std::string::npos) << problem->detail;
        EXPECT_EQ(res->get_header_value("X-Request-Id"), problem->request_id);
    }
    // The server still answers, on a new connection.
    auto ok = cli.Get("/test/ok");
    ASSERT_TRUE(ok);
    EXPECT_EQ(ok->status, 204);
    auto health = cli.Get("/healthz");
    ASSERT_TRUE(health);
    EXPECT_EQ(health->status, 200);
}

/// A connected loopback socket, or -1.
int connect_to(int port) {
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<uint16_t>(port));
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (fd >= 0 && ::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0) return fd;
    if (fd >= 0) ::close(fd);
    return -1;
}

/// Sends `request` on `fd` and returns what arrives until the server closes the connection
/// (bounded: 30 s).
std::string exchange(int fd, const std::string& request) {
    ::send(fd, request.data(), request.size(), MSG_NOSIGNAL);
    std::string out;
    char buf[4096];
    for (;;) {
        pollfd p{fd, POLLIN, 0};
        if (::poll(&p, 1, 30000) <= 0) break;
        const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
        if (n <= 0) break;
        out.append(buf, static_cast<size_t>(n));
    }
    ::close(fd);
    return out;
}

size_t count_of(const std::string& text, const std::string& what) {
    size_t n = 0;
    for (size_t at = text.find(what); at != std::string::npos; at = text.find(what, at + 1)) ++n;
    return n;
}

// The connection layer in process (so the sanitizer pass covers it; the integration tests in
// http_connections_test.cpp drive it from outside): pipelining with a prebuffered body, the
// head limits, the head deadline, and a connection reused after idling in the poll loop.
TEST(HttpWrapper, TheConnectionLayerAnswersPipelinedRequestsAndRefusesBadHeads) {
    InProcessServer server([](HttpServer&) {},
                           [](ServerConfig& c) {
                               c.request_head_timeout_s = 1;
                               c.max_request_head_bytes = 2048;
                               c.max_request_headers = 10;
                           });
    ASSERT_GT(server.port(), 0);
    // Three pipelined requests, the second with a body the loop receives before a thread.
    std::string requests = "GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n";
    requests +=
        "POST /v1/render HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
        "Content-Length: 2\r\n\r\n{}";
    requests += "GET /readyz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n";
    std::string reply = exchange(connect_to(server.port()), requests);
    EXPECT_EQ(count_of(reply, "HTTP/1.1 "), 3u) << reply;
    EXPECT_EQ(reply.rfind("HTTP/1.1 200", 0), 0u) << reply;
    EXPECT_NE(reply.find("HTTP/1.1 400"), std::string::npos) << reply;  // {} names no mesh
    // Over the head limits.
    reply = exchange(connect_to(server.port()),
                     "GET /healthz HTTP/1.1\r\nX-Big: " + std::string(3000, 'a') + "\r\n\r\n");
    EXPECT_EQ(reply.rfind("HTTP/1.1 431", 0), 0u) << reply;
    std::string many = "GET /healthz HTTP/1.1\r\n";
    for (int i = 0; i < 11; ++i) many += "X-A: 1\r\n";
    reply = exchange(connect_to(server.port()), many + "\r\n");
    EXPECT_EQ(reply.rfind("HTTP/1.1 431", 0), 0u) << reply;
    // A head that stops arriving: 408 at the 1 s head deadline.
    reply = exchange(connect_to(server.port()), "GET /healthz HTTP/1.1\r\nHost: x\r\n");
    EXPECT_EQ(reply.rfind("HTTP/1.1 408", 0), 0u) << reply;
    // A keep-alive connection idles in the loop between requests and is served again.
    httplib::Client cli("127.0.0.1", server.port());
    cli.set_keep_alive(true);
    for (int i = 0; i < 3; ++i) {
        auto res = cli.Get("/healthz");
        ASSERT_TRUE(res);
        EXPECT_EQ(res->status, 200);
    }
}

}  // namespace
}  // namespace kdrt::server
