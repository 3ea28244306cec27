// The HTTP front end in process (no server binary): what the route wrapper does when a handler
// throws. A test-only route (HttpServer::add_route_for_tests, never registered by kdrt-server)
// throws a std::exception and a non-std exception; both must become a 500 problem+json that
// names the request id, leaks nothing of the exception, closes the connection, and leaves the
// server serving.

#include <gtest/gtest.h>
#include <httplib.h>
#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <stdexcept>
#include <string>
#include <thread>

#include "http_server.h"
#include "kdrt/proto/problem.h"
#include "service.h"

namespace kdrt::server {
namespace {

namespace fs = std::filesystem;

/// A Service + HttpServer on an ephemeral loopback port, serving on a thread.
class InProcessServer {
public:
    explicit InProcessServer(const std::function<void(HttpServer&)>& add_routes) {
        static std::atomic<int> counter{0};
        dir_ = fs::temp_directory_path() / ("kdrt-wrapper-test-" + std::to_string(::getpid()) +
                                            "-" + std::to_string(counter++));
        fs::remove_all(dir_);
        ServerConfig config;
        config.cache_dir = (dir_ / "cache").string();
        config.threads = 1;
        config.http_threads = 2;
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

}  // namespace
}  // namespace kdrt::server
