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
    [[nodiscard]] uint64_t taken_after_answer() const {
        return front_.gauges()->taken_after_answer.load();
    }
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
        return send_raw("GET " + path + " HTTP/1.1\r\nHost: x\r\n\r\n") ? answer() : "";
    }
    bool send_raw(const std::string& bytes) {
        return ::send(fd_, bytes.data(), bytes.size(), MSG_NOSIGNAL) ==
               static_cast<ssize_t>(bytes.size());
    }
    /// The body of the next answer ("" when none came); bytes of the answers after it are kept
    /// for them.
    std::string answer() {
        char buf[4096];
        for (;;) {
            const size_t end = in_.find("\r\n\r\n");
            if (end != std::string::npos) {
                const size_t at = in_.find("Content-Length: ");
                const size_t length =
                    at == std::string::npos || at > end ? 0 : std::stoul(in_.substr(at + 16));
                if (in_.size() >= end + 4 + length) {
                    std::string body = in_.substr(end + 4, length);
                    in_.erase(0, end + 4 + length);
                    return body;
                }
            }
            const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
            if (n <= 0) return "";
            in_.append(buf, static_cast<size_t>(n));
        }
    }
    [[nodiscard]] int fd() const { return fd_; }

private:
    int fd_;
    std::string in_;  ///< received bytes of answers not yet returned
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

/// Answers "/first" once the test says its next request has been sent (so that it waits in the
/// socket as the answer goes out), every other request with its path and body.
class FollowFront {
public:
    FollowFront()
        : front(4, [this](httplib::Request& req, httplib::Response& res,
                          const httplib::ContentReader& reader) {
              std::string body;
              reader([&](const char* data, size_t size) {
                  body.append(data, size);
                  return true;
              });
              std::unique_lock lock(mutex);
              by.push_back(std::this_thread::get_id());
              if (req.path == "/first") {
                  inside = true;
                  cv.notify_all();
                  cv.wait_for(lock, 10s, [&] { return next_sent; });
              }
              res.status = 200;
              res.body = req.path + ":" + body;
          }) {}
    /// Waits until "/first" is being answered (false after 10 s).
    bool wait_inside() {
        std::unique_lock lock(mutex);
        return cv.wait_for(lock, 10s, [&] { return inside; });
    }
    /// Warms `client`'s connection up until all 4 workers are free, then sends "/first" and
    /// waits until it is being answered (its worker holds it until release()).
    void start_first(WorkerClient& client) {
        ASSERT_EQ(client.get("/warm"), "/warm:");
        ASSERT_TRUE(front.wait_idle(4)) << "the 4 workers did not all start";
        ASSERT_TRUE(client.send_raw("GET /first HTTP/1.1\r\nHost: x\r\n\r\n"));
        ASSERT_TRUE(wait_inside());
    }
    void release() {
        std::lock_guard lock(mutex);
        next_sent = true;
        cv.notify_all();
    }

    std::mutex mutex;
    std::condition_variable cv;
    bool inside = false, next_sent = false;
    std::vector<std::thread::id> by;
    WorkerFront front;
};

/// Sends `sent` while /first is answered (held by start_first), then `rest` once the worker is
/// free again: the worker must hand the connection back to the loop rather than take the
/// request (its wait sees `sent` only), and the loop answers "/second:hello" in the end.
void expect_handed_back(FollowFront& f, WorkerClient& client, const std::string& sent,
                        const std::string& rest) {
    const uint64_t taken = f.front.taken_after_answer();
    ASSERT_TRUE(client.send_raw(sent));
    f.release();
    EXPECT_EQ(client.answer(), "/first:");
    // The worker is free again once it has handed the connection back (not held by the rest).
    ASSERT_TRUE(f.front.wait_idle(4)) << "a worker is held by the request";
    ASSERT_TRUE(client.send_raw(rest));
    EXPECT_EQ(client.answer(), "/second:hello");
    EXPECT_EQ(f.front.taken_after_answer(), taken);
}

TEST(HttpFrontWorkers, ARequestWaitingAsItsConnectionsAnswerGoesOutIsTakenByThatWorker) {
    FollowFront f;
    WorkerClient client(f.front.port());
    ASSERT_NO_FATAL_FAILURE(f.start_first(client));
    const uint64_t taken = f.front.taken_after_answer();
    // A body of several reads (16 KB each), sent whole while /first is answered: its worker
    // finds the request as it finishes and takes it, body and all, without the loop. The body is
    // sent before the release (it fits in the loopback sockets' buffers), so the worker finds it
    // there within its wait however loaded the machine is (a body still coming after the wait
    // goes back to the loop: ABodyStillComingAfterTheWaitGoesBackToTheLoop).
    std::string body(60000, 'b');
    for (size_t i = 0; i < body.size(); i += 7) body[i] = static_cast<char>('a' + i % 26);
    ASSERT_TRUE(client.send_raw("POST /second HTTP/1.1\r\nHost: x\r\nContent-Length: " +
                                std::to_string(body.size()) + "\r\n\r\n" + body));
    f.release();
    EXPECT_EQ(client.answer(), "/first:");
    const std::string second = client.answer();
    EXPECT_TRUE(second == "/second:" + body) << "an answer of " << second.size() << " bytes";
    EXPECT_EQ(f.front.taken_after_answer(), taken + 1);
    // The next request on the connection is answered as well (by the loop or this worker).
    EXPECT_EQ(client.get("/third"), "/third:");
    std::lock_guard lock(f.mutex);
    ASSERT_EQ(f.by.size(), 4u);
    EXPECT_EQ(f.by[1], f.by[2]) << "/second went to another worker";
}

TEST(HttpFrontWorkers, APartOfAHeadWaitingAsTheAnswerGoesOutGoesBackToTheLoop) {
    FollowFront f;
    WorkerClient client(f.front.port());
    ASSERT_NO_FATAL_FAILURE(f.start_first(client));
    // Empty lines (ignored) and half of the next head: the worker reads them and hands the
    // connection back; the loop scans them again with the rest.
    ASSERT_NO_FATAL_FAILURE(expect_handed_back(
        f, client, "\r\nPOST /second HTTP/1.1\r\nHost: x\r\nContent-Len", "gth: 5\r\n\r\nhello"));
    // A head refused after the answer: 400 from the loop, the connection closed.
    ASSERT_TRUE(client.send_raw("GET /x HTTP/1.1\r\nHost: x\r\nbad header line\r\n\r\n"));
    char buf[256];
    const ssize_t n = ::recv(client.fd(), buf, sizeof buf, 0);
    ASSERT_GT(n, 12);
    EXPECT_EQ(std::string(buf, 12), "HTTP/1.1 400");
}

TEST(HttpFrontWorkers, ABodyStillComingAfterTheWaitGoesBackToTheLoop) {
    FollowFront f;
    WorkerClient client(f.front.port());
    ASSERT_NO_FATAL_FAILURE(f.start_first(client));
    // A whole head but only part of its small body: the worker does not wait on the rest (the
    // loop would have buffered it before giving the request to any thread), it hands the
    // connection back, and the loop answers once the body is complete.
    ASSERT_NO_FATAL_FAILURE(expect_handed_back(
        f, client, "POST /second HTTP/1.1\r\nHost: x\r\nContent-Length: 5\r\n\r\nhe", "llo"));
}

}  // namespace
}  // namespace kdrt::server
