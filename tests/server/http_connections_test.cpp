// The connection layer against a real kdrt-server: slow and idle clients hold no thread, the
// request head and body deadlines (408), the head limits (431), the connection limit (503),
// pipelining, ignored Range headers and refused Content-Encoding.

#include <gtest/gtest.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "http_test_util.h"

namespace kdrt::test {
namespace {

using namespace std::chrono_literals;

/// Everything received on `fd` until the peer closes it or `timeout` passes.
std::string receive_until_closed(int fd, std::chrono::milliseconds timeout) {
    const auto end = std::chrono::steady_clock::now() + timeout;
    std::string out;
    char buf[4096];
    for (;;) {
        const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
            end - std::chrono::steady_clock::now());
        if (left.count() <= 0) break;
        pollfd p{fd, POLLIN, 0};
        if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) break;
        const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
        if (n <= 0) break;
        out.append(buf, static_cast<size_t>(n));
    }
    return out;
}

/// One whole response read from `fd` (its head, then Content-Length bytes of body), or what
/// arrived before the peer closed or `timeout` passed. A single recv() may return a response's
/// head without its body (the server writes them separately), which must not be left behind
/// for the next request's read.
std::string receive_response(int fd, std::chrono::milliseconds timeout) {
    const auto end = std::chrono::steady_clock::now() + timeout;
    std::string out;
    char buf[4096];
    for (;;) {
        const size_t head_end = out.find("\r\n\r\n");
        if (head_end != std::string::npos) {
            size_t length = 0;
            const size_t at = out.find("Content-Length: ");
            if (at != std::string::npos && at < head_end)
                length = std::stoul(out.substr(at + 16, out.find("\r\n", at) - at - 16));
            if (out.size() >= head_end + 4 + length) return out;
        }
        const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
            end - std::chrono::steady_clock::now());
        if (left.count() <= 0) return out;
        pollfd p{fd, POLLIN, 0};
        if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) return out;
        const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
        if (n <= 0) return out;
        out.append(buf, static_cast<size_t>(n));
    }
}

/// A count of the complete HTTP responses in `text` (status lines).
size_t response_count(const std::string& text) {
    size_t count = 0;
    for (size_t at = text.find("HTTP/1.1 "); at != std::string::npos;
         at = text.find("HTTP/1.1 ", at + 1))
        ++count;
    return count;
}

/// Open sockets, closed on destruction.
struct Sockets {
    std::vector<int> fds;
    ~Sockets() {
        for (const int fd : fds) ::close(fd);
    }
};

constexpr const char* kHealthz = "GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n";

TEST(HttpConnections, SlowAndIdleClientsDoNotStarveOtherRequests) {
    TempDir dir;
    // 4 threads; slow and idle clients well beyond that. Deadlines long enough that nothing is
    // cut while the test runs: every connection below is still open when /healthz is asked.
    ServerProcess server({.cache_dir = dir.path() / "cache",
                          .args = {"--http-threads", "4", "--keep-alive-timeout-s", "60",
                                   "--request-head-timeout-s", "60", "--request-timeout-s", "60"}});
    ASSERT_TRUE(server.running());
    Sockets held;
    constexpr size_t kEach = 24;
    for (size_t i = 0; i < kEach; ++i) {
        // A head that never ends.
        const int slow_head = connect_loopback(server.port());
        ASSERT_GE(slow_head, 0);
        held.fds.push_back(slow_head);
        ASSERT_TRUE(send_all(slow_head, "GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: a"));
        // A small body that never ends.
        const int slow_body = connect_loopback(server.port());
        ASSERT_GE(slow_body, 0);
        held.fds.push_back(slow_body);
        ASSERT_TRUE(send_all(slow_body,
                             "POST /v1/render HTTP/1.1\r\nHost: x\r\nContent-Type: "
                             "application/json\r\nContent-Length: 400\r\n\r\n{\"mesh\":"));
        // An idle keep-alive connection after one answered request.
        const int idle = connect_loopback(server.port());
        ASSERT_GE(idle, 0);
        held.fds.push_back(idle);
        ASSERT_TRUE(send_all(idle, kHealthz));
    }
    // Every idle connection got its answer and stays open.
    for (size_t i = 0; i < kEach; ++i) {
        const std::string answer = receive_response(held.fds[3 * i + 2], 10s);
        ASSERT_FALSE(answer.empty()) << "idle connection " << i << " got no answer";
        EXPECT_EQ(answer.rfind("HTTP/1.1 200", 0), 0u) << answer;
    }
    // Fresh requests still answer, on fresh connections and on the idle ones.
    for (int round = 0; round < 8; ++round) {
        const std::string reply = raw_exchange(
            server.port(), "GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", 10s);
        EXPECT_EQ(reply.rfind("HTTP/1.1 200", 0), 0u) << "round " << round << ": " << reply;
    }
    const int reused = held.fds[2];
    ASSERT_TRUE(send_all(reused, "GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"));
    EXPECT_EQ(receive_until_closed(reused, 10s).rfind("HTTP/1.1 200", 0), 0u);
    auto metrics = server.client()->Get("/metrics");
    ASSERT_TRUE(metrics);
    EXPECT_EQ(metrics->status, 200);
}

TEST(HttpConnections, TricklingHeadIsCutWith408AtTheHeadDeadline) {
    TempDir dir;
    // A byte every 100 ms never trips the 1 s per-read timeout; the 2 s head deadline cuts it.
    ServerProcess server({.cache_dir = dir.path() / "cache",
                          .args = {"--read-timeout-s", "1", "--request-head-timeout-s", "2"}});
    ASSERT_TRUE(server.running());
    const int fd = connect_loopback(server.port());
    ASSERT_GE(fd, 0);
    std::atomic<bool> done{false};
    std::thread trickle([&] {
        const std::string head = "GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: ";
        ASSERT_TRUE(send_all(fd, head));
        for (int i = 0; i < 300 && !done; ++i) {
            if (::send(fd, "a", 1, MSG_NOSIGNAL) != 1) break;
            std::this_thread::sleep_for(100ms);
        }
    });
    const std::string reply = receive_until_closed(fd, 20s);
    done = true;
    trickle.join();
    ::close(fd);
    EXPECT_EQ(reply.rfind("HTTP/1.1 408", 0), 0u) << reply;
    EXPECT_NE(reply.find("urn:kdrt:problem:request-timeout"), std::string::npos) << reply;
    EXPECT_NE(reply.find("request_head_timeout_s"), std::string::npos) << reply;
    EXPECT_NE(server.log().find("request refused"), std::string::npos);
}

/// A POST whose 100-byte JSON body trickles in: cut at the request deadline with 408, whether
/// the body is awaited by the poll() loop (prebuffered) or on a thread (no prebuffering).
void expect_trickling_body_cut(const std::vector<std::string>& extra_args) {
    TempDir dir;
    std::vector<std::string> args = {"--read-timeout-s", "1", "--request-timeout-s", "2"};
    args.insert(args.end(), extra_args.begin(), extra_args.end());
    ServerProcess server({.cache_dir = dir.path() / "cache", .args = args});
    ASSERT_TRUE(server.running());
    const int fd = connect_loopback(server.port());
    ASSERT_GE(fd, 0);
    std::atomic<bool> done{false};
    std::thread trickle([&] {
        ASSERT_TRUE(send_all(fd,
                             "POST /v1/render HTTP/1.1\r\nHost: x\r\nContent-Type: "
                             "application/json\r\nContent-Length: 100\r\n\r\n{"));
        for (int i = 0; i < 99 && !done; ++i) {
            if (::send(fd, " ", 1, MSG_NOSIGNAL) != 1) break;
            std::this_thread::sleep_for(100ms);
        }
    });
    const std::string reply = receive_until_closed(fd, 20s);
    done = true;
    trickle.join();
    ::close(fd);
    EXPECT_EQ(reply.rfind("HTTP/1.1 408", 0), 0u) << reply;
    EXPECT_NE(reply.find("urn:kdrt:problem:request-timeout"), std::string::npos) << reply;
    EXPECT_NE(reply.find("request_timeout_s"), std::string::npos) << reply;
}

TEST(HttpConnections, TricklingSmallBodyIsCutWith408) { expect_trickling_body_cut({}); }

TEST(HttpConnections, TricklingBodyReadOnAThreadIsCutWith408) {
    expect_trickling_body_cut({"--request-prebuffer-bytes", "0"});
}

TEST(HttpConnections, OversizedHeadsAre431) {
    TempDir dir;
    ServerProcess server(
        {.cache_dir = dir.path() / "cache",
         .args = {"--max-request-head-bytes", "4K", "--max-request-headers", "20"}});
    ASSERT_TRUE(server.running());
    // One big header, sent in full before the reply is read.
    std::string reply = raw_exchange(
        server.port(),
        "GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: " + std::string(5000, 'a') + "\r\n\r\n", 10s);
    EXPECT_EQ(reply.rfind("HTTP/1.1 431", 0), 0u) << reply;
    EXPECT_NE(reply.find("max_request_head_bytes"), std::string::npos) << reply;
    // Many small headers (well under 4 KiB).
    std::string head = "GET /healthz HTTP/1.1\r\nHost: x\r\n";
    for (int i = 0; i < 21; ++i) head.append("X-").append(std::to_string(i)).append(": 1\r\n");
    reply = raw_exchange(server.port(), head + "\r\n", 10s);
    EXPECT_EQ(reply.rfind("HTTP/1.1 431", 0), 0u) << reply;
    EXPECT_NE(reply.find("more than 20 header lines (max_request_headers)"), std::string::npos)
        << reply;
    // 64 MiB of headers are never buffered: the reply comes once the limit is passed.
    const int fd = connect_loopback(server.port());
    ASSERT_GE(fd, 0);
    std::string flood = "GET /healthz HTTP/1.1\r\n";
    while (flood.size() < (1u << 20)) flood += "X-Flood: 1\r\n";
    send_all(fd, flood);  // the server may close before all of it is taken
    reply = receive_until_closed(fd, 10s);
    ::close(fd);
    EXPECT_EQ(reply.rfind("HTTP/1.1 431", 0), 0u) << reply.substr(0, 200);
    // Exactly at the limits is fine.
    head = "GET /healthz HTTP/1.1\r\nConnection: close\r\n";
    for (int i = 0; i < 19; ++i) head.append("X-").append(std::to_string(i)).append(": 1\r\n");
    reply = raw_exchange(server.port(), head + "\r\n", 10s);
    EXPECT_EQ(reply.rfind("HTTP/1.1 200", 0), 0u) << reply;
}

TEST(HttpConnections, ConnectionsBeyondTheLimitGet503) {
    TempDir dir;
    // The held connections must not reach the keep-alive timeout (2 s) on a slow machine.
    ServerProcess server({.cache_dir = dir.path() / "cache",
                          .args = {"--max-connections", "4", "--keep-alive-timeout-s", "60"}});
    ASSERT_TRUE(server.running());
    // Four connections held open, each answered 200. The start-up's /readyz connection counts
    // until the server has seen its client close it, so a fourth connection may still be refused
    // (503) just after start: it is closed and tried again until the server has seen that close.
    Sockets held;
    for (int attempt = 0; held.fds.size() < 4 && attempt < 200; ++attempt) {
        const int fd = connect_loopback(server.port());
        ASSERT_GE(fd, 0);
        ASSERT_TRUE(send_all(fd, kHealthz));
        std::string head;  // at least the status line's first 12 bytes
        while (head.size() < 12) {
            pollfd p{fd, POLLIN, 0};
            ASSERT_GT(::poll(&p, 1, 10000), 0);
            char buf[1024];
            const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
            ASSERT_GT(n, 0);
            head.append(buf, static_cast<size_t>(n));
        }
        if (head.rfind("HTTP/1.1 200", 0) == 0) {
            held.fds.push_back(fd);
            continue;
        }
        ::close(fd);
        ASSERT_EQ(head.rfind("HTTP/1.1 503", 0), 0u) << head;
        std::this_thread::sleep_for(10ms);
    }
    ASSERT_EQ(held.fds.size(), 4u);
    const std::string reply = raw_exchange(server.port(), kHealthz, 10s);
    EXPECT_EQ(reply.rfind("HTTP/1.1 503", 0), 0u) << reply;
    EXPECT_NE(reply.find("Retry-After: 1"), std::string::npos) << reply;
    EXPECT_NE(reply.find("(max_connections)"), std::string::npos) << reply;
    ::close(held.fds.back());
    held.fds.pop_back();
    std::string again;
    for (int attempt = 0; attempt < 200 && again.rfind("HTTP/1.1 200", 0) != 0; ++attempt) {
        std::this_thread::sleep_for(10ms);  // until the server has seen the close
        again = raw_exchange(server.port(),
                             "GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", 10s);
    }
    EXPECT_EQ(again.rfind("HTTP/1.1 200", 0), 0u) << again;
}

TEST(HttpConnections, PipelinedRequestsAreAllAnswered) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    ASSERT_TRUE(server.running());
    std::string requests;
    for (int i = 0; i < 5; ++i) requests += kHealthz;
    requests += "GET /readyz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n";
    const std::string reply = raw_exchange(server.port(), requests, 10s);
    EXPECT_EQ(response_count(reply), 6u) << reply;
    EXPECT_NE(reply.find("\"status\":\"ready\""), std::string::npos) << reply;
}

TEST(HttpConnections, RangeHeadersAreIgnored) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    std::string ranges = "bytes=0-1";
    for (int i = 1; i < 1000; ++i)
        ranges.append(",").append(std::to_string(i)).append("-").append(std::to_string(i));
    auto res = cli->Get("/healthz", {{"Range", ranges}});
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 200);
    EXPECT_EQ(res->body, "{\"status\":\"ok\"}");
    EXPECT_FALSE(res->has_header("Content-Range"));
}

TEST(HttpConnections, CompressedRequestBodiesAre415) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    auto res =
        cli->Post("/v1/meshes", {{"Content-Encoding", "gzip"}}, std::string(100, 'x'), "model/obj");
    auto p = expect_problem(res, 415);
    EXPECT_EQ(p.kind, proto::ProblemKind::kUnsupportedMediaType);
    EXPECT_NE(p.detail.find("Content-Encoding \"gzip\" is not accepted"), std::string::npos)
        << p.detail;
    EXPECT_EQ(res->get_header_value("Accept-Encoding"), "identity");
    // identity is no encoding.
    res = cli->Post("/v1/meshes", {{"Content-Encoding", "identity"}}, "v 0 0 0\n", "model/obj");
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 422);
}

}  // namespace
}  // namespace kdrt::test
