#pragma once
/// The HTTP front end: binds, serves the API v1 routes on cpp-httplib, stops gracefully.
/// httplib itself stays inside server/http_*.cpp (this header does not include it).

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "kdrt/proto/result.h"
#include "service.h"

namespace kdrt::server {

/// A registered route: its method and path template, e.g. {"POST", "/v1/meshes/{id}/intersect"}.
struct RouteInfo {
    std::string method;
    std::string path;
};

class HttpServer {
public:
    /// Configures the server from service.config (threads, timeouts, limits, routes).
    explicit HttpServer(Service& service);
    ~HttpServer();
    HttpServer(const HttpServer&) = delete;
    HttpServer& operator=(const HttpServer&) = delete;

    /// Binds HOST:PORT (port 0: any free port). Returns the bound port.
    [[nodiscard]] proto::Result<int, std::string> bind(const std::string& host, int port);
    /// Accepts and serves connections until stop(); then waits for in-flight requests. False if
    /// the listening socket failed.
    bool serve();
    /// Stops accepting; serve() returns once the requests in flight are answered.
    void stop();
    /// Every route the server answers, in registration order (tests compare it with
    /// proto/openapi.yaml).
    [[nodiscard]] std::vector<RouteInfo> routes() const;

    /// For in-process tests only (kdrt-server never calls it, so no such route exists in the
    /// service): answers GET `path` by calling `action` inside the same per-request context and
    /// exception handling as the API routes, so a test can make a handler throw. Call before
    /// serve(); the route is not listed by routes().
    void add_route_for_tests(const std::string& path, std::function<void()> action);

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

/// The cpp-httplib version the server was built against (for kdrt_build_info).
[[nodiscard]] std::string httplib_version();

}  // namespace kdrt::server
