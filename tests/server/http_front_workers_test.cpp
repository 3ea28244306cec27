// Which of the HTTP front's worker threads answers a request (server/http/http_front.cpp): the
// most recently idle one, so that a client's requests in turn on its connection stay on one warm
// thread, while requests at once still get a thread each. An HttpFront in this process on a
// loopback port.

#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <condition_variable>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "http/http_front.h"

namespace kdrt::server {
namespace {

using namespace std::chrono_literals;

/// A front with `threads` workers whose answer is `answer`, served on its own thread.
class WorkerFront {
public:
    WorkerFront(unsigned threads, AnswerRequest answer)
        : front_(
              [threads] {
                  ConnectionLimits limits;
                  limits.threads = threads;
                  return limits;
              }(),
              [](int, std::string_view, const std::string&) { return std::string("{}"); },
              std::move(answer), [](const httplib::Request&, const httplib::Response&) {}) {
        auto port = front_.bind("127.0.0.1", 0, 64);
        EXPECT_TRUE(port.ok());
        port_ = port.ok() ? *port : 0;
        thread_ = std::thread([this] { front_.serve(); });
    }
    ~WorkerFront() {
        front_.stop();
        thread_.join();
    }
    [[nodiscard]] int port() const { return port_; }
    /// True once `n` workers are started and free, false if that takes over 10 s.
    bool wait_idle(size_t n) const {
        const auto gauges = front_.gauges();
        for (int i = 0; i < 10000; ++i) {
            if (gauges->idle.load() == n) return true;
            std::this_thread::sleep_for(1ms);
        }
        return false;
    }

private:
    HttpFront front_;
    int port_ = 0;
    std::thread thread_;
};

/// A keep-alive client connection.
class WorkerClient {
public:
    explicit WorkerClient(int port) : fd_(::socket(AF_INET, SOCK_STREAM, 0)) {
        sockaddr_in a{};
        a.sin_family = AF_INET;
        a.sin_port = htons(static_cast<uint16_t>(port));
        a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        EXPECT_EQ(::connect(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
        int yes = 1;
        ::setsockopt(fd_, IPPROTO_TCP, TCP_NODELAY, &yes, sizeof yes);
        timeval tv{10, 0};
        ::setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    }
    ~WorkerClient() { ::close(fd_); }
    WorkerClient(const WorkerClient&) = delete;
    WorkerClient& operator=(const WorkerClient&) = delete;

    /// GET `path`; the answer's body ("" when none came).
    std::string get(const std::string& path) {
        const std::string request = "GET " + path + " HTTP/1.1\r\nHost: x\r\n\r\n";
        if (::send(fd_, request.data(), request.size(), MSG_NOSIGNAL) !=
            static_cast<ssize_t>(request.size()))
            return "";
        std::string in;
        char buf[4096];
        for (;;) {
            const size_t end = in.find("\r\n\r\n");
            if (end != std::string::npos) {
                const size_t at = in.find("Content-Length: ");
                const size_t length = at == std::string::npos ? 0 : std::stoul(in.substr(at + 16));
                if (in.size() >= end + 4 + length) return in.substr(end + 4, length);
            }
            const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
            if (n <= 0) return "";
            in.append(buf, static_cast<size_t>(n));
        }
    }

private:
    int fd_;
};

TEST(HttpFrontWorkers, RequestsInTurnStayOnTheThreadThatAnsweredTheLastOne) {
    std::mutex mutex;
    std::vector<std::thread::id> answered_by;
    WorkerFront front(
        8, [&](httplib::Request&, httplib::Response& res, const httplib::ContentReader&) {
            {
                std::lock_guard lock(mutex);
                answered_by.push_back(std::this_thread::get_id());
            }
            res.status = 200;
            res.body = "ok";
        });
    WorkerClient client(front.port());
    // A worker that starts late lists itself last and takes the next request, so the test
    // begins once all eight are started and free (the gauge behind kdrt_http_threads_idle);
    // from then on the thread that answered a request is the next one's.
    ASSERT_EQ(client.get("/a"), "ok");
    ASSERT_TRUE(front.wait_idle(8)) << "the 8 workers did not all start";
    {
        std::lock_guard lock(mutex);
        answered_by.clear();
    }
    for (int i = 0; i < 30; ++i) ASSERT_EQ(client.get("/b"), "ok") << i;
    std::lock_guard lock(mutex);
    ASSERT_EQ(answered_by.size(), 30u);
    EXPECT_EQ(std::set<std::thread::id>(answered_by.begin(), answered_by.end()).size(), 1u)
        << "requests in turn went to several of the 8 workers";
}

TEST(HttpFrontWorkers, RequestsAtOnceStillGetAThreadEach) {
    constexpr int kAtOnce = 4;
    std::mutex mutex;
    std::condition_variable cv;
    int inside = 0;
    std::set<std::thread::id> answered_by;
    // Each answer waits until all kAtOnce requests are being answered: they must be on
    // kAtOnce threads at once (or the wait times out and the answer says so).
    WorkerFront front(
        8, [&](httplib::Request&, httplib::Response& res, const httplib::ContentReader&) {
            std::unique_lock lock(mutex);
            answered_by.insert(std::this_thread::get_id());
            ++inside;
            cv.notify_all();
            const bool all = cv.wait_for(lock, 10s, [&] { return inside >= kAtOnce; });
            res.status = 200;
            res.body = all ? "together" : "alone";
        });
    std::vector<std::string> got(kAtOnce);
    std::vector<std::thread> clients;
    for (int c = 0; c < kAtOnce; ++c)
        clients.emplace_back([&, c] {
            WorkerClient client(front.port());
            got[c] = client.get("/c");
        });
    for (std::thread& t : clients) t.join();
    for (int c = 0; c < kAtOnce; ++c) EXPECT_EQ(got[c], "together") << "client " << c;
    std::lock_guard lock(mutex);
    EXPECT_EQ(answered_by.size(), static_cast<size_t>(kAtOnce));
}

}  // namespace
}  // namespace kdrt::server
