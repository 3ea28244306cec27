#include "fake_server.h"

#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include "kdrt/proto/problem.h"

namespace kdrt::test {

FakeServer::FakeServer(const std::function<void(httplib::Server&)>& setup, int port) {
    // stop() waits for connection threads, and an idle keep-alive connection holds one for this
    // long.
    http_.set_keep_alive_timeout(1);
    setup(http_);
    if (port == 0) {
        port_ = http_.bind_to_any_port("127.0.0.1");
    } else {
        port_ = http_.bind_to_port("127.0.0.1", port) ? port : -1;
    }
    if (port_ <= 0) {
        ADD_FAILURE() << "the fake server cannot bind 127.0.0.1:" << port;
        return;
    }
    thread_ = std::thread([this] { http_.listen_after_bind(); });
    // 0.11.4 has no wait_until_ready: poll is_running (bounded).
    for (int i = 0; i < 1000 && !http_.is_running(); ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
}

FakeServer::~FakeServer() {
    http_.stop();
    if (thread_.joinable()) thread_.join();
}

FaultyProxy::FaultyProxy(int upstream_port, int unavailable_first, int retry_after_s, int status)
    : upstream_port_(upstream_port),
      unavailable_first_(unavailable_first),
      retry_after_s_(retry_after_s),
      status_(status) {
    server_ = std::make_unique<FakeServer>([this](httplib::Server& http) {
        const auto handler = [this](const httplib::Request& req, httplib::Response& res) {
            handle(req, res);
        };
        http.Get(".*", handler);
        http.Post(".*", handler);
        http.Delete(".*", handler);
    });
}

std::vector<std::string> FaultyProxy::log() const {
    std::lock_guard lock(mutex_);
    return log_;
}

void FaultyProxy::handle(const httplib::Request& req, httplib::Response& res) {
    const int index = requests_.fetch_add(1);
    if (index < unavailable_first_) {
        proto::Problem p;
        p.kind = proto::ProblemKind::kOverCapacity;
        p.detail = "injected " + std::to_string(status_) + " number " + std::to_string(index + 1);
        p.instance = req.path;
        p.request_id = "fake";
        if (retry_after_s_ >= 0) {
            p.retry_after = static_cast<uint32_t>(retry_after_s_);
            res.set_header("Retry-After", std::to_string(retry_after_s_));
        }
        res.status = status_;
        res.set_content(proto::encode_problem(p), std::string(proto::kProblemMediaType));
    } else {
        httplib::Client upstream("127.0.0.1", upstream_port_);
        upstream.set_read_timeout(120, 0);
        upstream.set_write_timeout(120, 0);
        httplib::Headers headers;
        for (const char* name : {"Authorization", "Prefer"})
            if (req.has_header(name)) headers.emplace(name, req.get_header_value(name));
        const std::string type = req.get_header_value("Content-Type");
        httplib::Result forwarded = req.method == "GET" ? upstream.Get(req.path, headers)
                                    : req.method == "DELETE"
                                        ? upstream.Delete(req.path, headers)
                                        : upstream.Post(req.path, headers, req.body, type);
        if (!forwarded) {
            res.status = 502;
            res.set_content("upstream failed: " + httplib::to_string(forwarded.error()),
                            "text/plain");
        } else {
            res.status = forwarded->status;
            for (const char* name : {"Retry-After", "Location", "X-Request-Id"})
                if (forwarded->has_header(name))
                    res.set_header(name, forwarded->get_header_value(name));
            res.set_content(forwarded->body, forwarded->get_header_value("Content-Type"));
        }
    }
    std::lock_guard lock(mutex_);
    log_.push_back(req.method + " " + req.path + " -> " + std::to_string(res.status));
}

DropServer::DropServer() {
    fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t len = sizeof addr;
    if (fd_ < 0 || ::bind(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0 ||
        ::listen(fd_, 16) != 0 ||
        ::getsockname(fd_, reinterpret_cast<sockaddr*>(&addr), &len) != 0) {
        ADD_FAILURE() << "DropServer cannot listen";
        return;
    }
    port_ = ntohs(addr.sin_port);
    thread_ = std::thread([this] {
        while (!stop_.load()) {
            pollfd p{fd_, POLLIN, 0};
            if (::poll(&p, 1, 20) <= 0) continue;
            const int conn = ::accept4(fd_, nullptr, nullptr, SOCK_CLOEXEC);
            if (conn < 0) continue;
            connections_.fetch_add(1);
            // Read until the end of the request head (or 1 s), then hang up without a word.
            std::string head;
            char buf[4096];
            for (int i = 0; i < 50 && head.find("\r\n\r\n") == std::string::npos; ++i) {
                pollfd c{conn, POLLIN, 0};
                if (::poll(&c, 1, 20) <= 0) continue;
                const ssize_t n = ::recv(conn, buf, sizeof buf, 0);
                if (n <= 0) break;
                head.append(buf, static_cast<size_t>(n));
            }
            ::close(conn);
        }
    });
}

DropServer::~DropServer() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
    if (fd_ >= 0) ::close(fd_);
}

int unused_port() {
    const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t len = sizeof addr;
    if (::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
        ::close(fd);
        return 0;  // what getsockname reports for an unbound socket
    }
    ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
    ::close(fd);
    return ntohs(addr.sin_port);
}

}  // namespace kdrt::test
