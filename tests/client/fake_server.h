#pragma once
// Stand-ins for kdrt-server in the client tests, for answers a healthy server never gives:
//   FakeServer   an httplib server on 127.0.0.1 with handlers the test registers;
//   FaultyProxy  forwards to a real kdrt-server after answering the first requests with 503;
//   DropServer   a raw TCP listener that reads a request and closes the connection unanswered.

#include <httplib.h>

#include <atomic>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

namespace kdrt::test {

class FakeServer {
public:
    /// `setup` registers the handlers. Binds 127.0.0.1:`port` (0: any free port) and serves on a
    /// thread until destruction. Fails the test if it cannot bind.
    explicit FakeServer(const std::function<void(httplib::Server&)>& setup, int port = 0);
    ~FakeServer();
    FakeServer(const FakeServer&) = delete;
    FakeServer& operator=(const FakeServer&) = delete;

    [[nodiscard]] int port() const noexcept { return port_; }
    [[nodiscard]] std::string url() const { return "http://127.0.0.1:" + std::to_string(port_); }

private:
    httplib::Server http_;
    std::thread thread_;
    int port_ = 0;
};

/// Forwards every request to the kdrt-server on 127.0.0.1:`upstream_port`, except that the first
/// `unavailable_first` requests get 503 (problem+json, over capacity) with `Retry-After:
/// retry_after_s` (no header when negative). `status` replaces 503 as the injected status (502
/// or 504: what a reverse proxy answers when the replica behind it failed).
class FaultyProxy {
public:
    FaultyProxy(int upstream_port, int unavailable_first, int retry_after_s = 1, int status = 503);

    [[nodiscard]] std::string url() const { return server_->url(); }
    /// Requests received so far.
    [[nodiscard]] int requests() const noexcept { return requests_.load(); }
    /// "METHOD PATH -> STATUS" per request, in arrival order.
    [[nodiscard]] std::vector<std::string> log() const;

private:
    void handle(const httplib::Request& req, httplib::Response& res);

    int upstream_port_;
    int unavailable_first_;
    int retry_after_s_;
    int status_;
    std::atomic<int> requests_{0};
    mutable std::mutex mutex_;
    std::vector<std::string> log_;
    std::unique_ptr<FakeServer> server_;  // last: destroyed (joined) first
};

/// Accepts connections on 127.0.0.1 (any free port), reads the request head and closes the
/// connection without answering: the client sees a transport error after sending.
class DropServer {
public:
    DropServer();
    ~DropServer();
    DropServer(const DropServer&) = delete;
    DropServer& operator=(const DropServer&) = delete;

    [[nodiscard]] std::string url() const { return "http://127.0.0.1:" + std::to_string(port_); }
    [[nodiscard]] int connections() const noexcept { return connections_.load(); }

private:
    int fd_ = -1;
    int port_ = 0;
    std::atomic<bool> stop_{false};
    std::atomic<int> connections_{0};
    std::thread thread_;
};

/// A port on 127.0.0.1 that nothing listens on (bound once, then released).
int unused_port();

}  // namespace kdrt::test
