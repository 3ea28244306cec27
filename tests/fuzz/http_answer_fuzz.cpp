// The client's own HTTP/1.1 answer reader (client/src/http_direct.cpp: status line, headers,
// Content-Length, chunked and close framing, 1xx answers), which reads every ray-batch and render
// answer. The input is the server's whole answer: a thread of this process accepts the client's
// loopback connection, reads its request head, writes the input and closes.
// Oracles: a read answer has a status of 200-599 and a body no longer than the input and the
// client's limit; a refused one is a read or protocol failure that says what was wrong.

#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <chrono>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "fuzz_check.h"
#include "http_direct.h"

namespace {

constexpr size_t kMaxBody = 2048;

/// The loopback server: one connection at a time, answered with `answer`.
class Peer {
public:
    Peer() {
        listen_fd_ = ::socket(AF_INET, SOCK_STREAM, 0);
        sockaddr_in addr{};
        addr.sin_family = AF_INET;
        addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        kdrt::fuzz::require(::bind(listen_fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) ==
                                0 &&
                            ::listen(listen_fd_, 16) == 0);
        socklen_t len = sizeof addr;
        ::getsockname(listen_fd_, reinterpret_cast<sockaddr*>(&addr), &len);
        port_ = ntohs(addr.sin_port);
        std::thread([this] { serve(); }).detach();
    }

    [[nodiscard]] int port() const noexcept { return port_; }

    void set_answer(std::string answer) {
        std::lock_guard lock(mutex_);
        answer_ = std::move(answer);
    }

private:
    void serve() {
        for (;;) {
            const int fd = ::accept(listen_fd_, nullptr, nullptr);
            if (fd < 0) continue;
            timeval timeout{2, 0};
            ::setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &timeout, sizeof timeout);
            ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof timeout);
            std::string request;
            char buffer[1024];
            while (request.find("\r\n\r\n") == std::string::npos) {
                const ssize_t n = ::recv(fd, buffer, sizeof buffer, 0);
                if (n <= 0) break;
                request.append(buffer, static_cast<size_t>(n));
            }
            std::string answer;
            {
                std::lock_guard lock(mutex_);
                answer = answer_;
            }
            size_t sent = 0;
            while (sent < answer.size()) {
                const ssize_t n =
                    ::send(fd, answer.data() + sent, answer.size() - sent, MSG_NOSIGNAL);
                if (n <= 0) break;
                sent += static_cast<size_t>(n);
            }
            ::close(fd);
        }
    }

    int listen_fd_ = -1;
    int port_ = 0;
    std::mutex mutex_;
    std::string answer_;
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    static Peer peer;
    peer.set_answer(std::string(reinterpret_cast<const char*>(data), size));
    detail::DirectConnection connection({.host = "127.0.0.1",
                                         .port = peer.port(),
                                         .host_header = "127.0.0.1",
                                         .token = "t",
                                         .connect_timeout = std::chrono::milliseconds(2000),
                                         .io_timeout = std::chrono::milliseconds(2000)});
    detail::DirectResponse response;
    std::string why;
    const detail::DirectFailure failure =
        connection.request("GET", "/v1/jobs/x/result", "", {}, kMaxBody, response, why);
    if (failure == detail::DirectFailure::kNone) {
        fuzz::require(response.status >= 200 && response.status <= 599);
        fuzz::require(response.body().size() <= size && response.body().size() <= kMaxBody);
    } else {
        fuzz::require(failure == detail::DirectFailure::kRead ||
                      failure == detail::DirectFailure::kProtocol);
        fuzz::require(!why.empty());
    }
    return 0;
}
