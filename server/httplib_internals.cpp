#include "httplib_internals.h"

#include <arpa/inet.h>
#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>

#include <cerrno>
#include <optional>
#include <string>

#include "http_util.h"

// httplib's own Server::process_and_close_socket (the keep-alive loop that reads and answers the
// requests of one connection, then closes it) is private, so the override below cannot call it
// as `httplib::Server::process_and_close_socket(sock)`, and a call through a member pointer would
// dispatch back to the override. It is called here, non-virtually, by the symbol libcpp-httplib
// exports for it (Itanium C++ ABI: `this` is the first argument). The version check in the header
// pins the library this was checked against. The alternatives: reimplementing httplib's
// keep-alive loop (a second copy of code we do not own), or scanning /proc/self/fd for a socket
// whose two ends match the request's addresses (a directory scan per connection, and a lookup
// by address rather than the socket httplib actually serves).
bool kdrt_httplib_serve_connection(httplib::Server* server, socket_t sock) __asm__(
    "_ZN7httplib6Server24process_and_close_socketEi");

namespace kdrt::server {
namespace {

/// The socket of the connection this thread is serving (httplib serves a connection on one
/// thread from accept to close), or -1.
thread_local socket_t t_connection_socket = -1;

/// The numeric host and port of a socket address, as httplib formats remote_addr/local_addr.
bool numeric_address(const sockaddr_storage& addr, socklen_t len, std::string& host, int& port) {
    char buffer[NI_MAXHOST];
    if (::getnameinfo(reinterpret_cast<const sockaddr*>(&addr), len, buffer, sizeof buffer, nullptr,
                      0, NI_NUMERICHOST) != 0)
        return false;
    host = buffer;
    if (addr.ss_family == AF_INET)
        port = ntohs(reinterpret_cast<const sockaddr_in*>(&addr)->sin_port);
    else if (addr.ss_family == AF_INET6)
        port = ntohs(reinterpret_cast<const sockaddr_in6*>(&addr)->sin6_port);
    else
        return false;
    return true;
}

/// True when `fd` is a connected TCP socket whose two ends are the request's.
bool is_connection_of(int fd, const httplib::Request& req) {
    sockaddr_storage addr{};
    socklen_t len = sizeof addr;
    std::string host;
    int port = 0;
    if (::getpeername(fd, reinterpret_cast<sockaddr*>(&addr), &len) != 0) return false;
    if (!numeric_address(addr, len, host, port) || port != req.remote_port ||
        host != req.remote_addr)
        return false;
    len = sizeof addr;
    if (::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len) != 0) return false;
    return numeric_address(addr, len, host, port) && port == req.local_port &&
           host == req.local_addr;
}

/// The socket `req` arrived on, when its body may be read from it directly: a Content-Length,
/// no Transfer-Encoding or Content-Encoding, served by a ConnectionServer on this thread, and
/// the socket's two ends are the request's (a check that costs two system calls).
std::optional<socket_t> direct_socket(const httplib::Request& req) {
    if (!req.has_header("Content-Length") || req.has_header("Transfer-Encoding"))
        return std::nullopt;
    const std::string encoding = req.get_header_value("Content-Encoding");
    if (!encoding.empty() && encoding != "identity") return std::nullopt;
    if (req.remote_port <= 0 || req.local_port <= 0) return std::nullopt;
    const socket_t fd = t_connection_socket;
    if (fd < 0 || !is_connection_of(fd, req)) return std::nullopt;
    return fd;
}

/// recv() of up to `size` bytes, waiting up to `timeout_s` for data (like httplib's read
/// timeout).
ptrdiff_t receive_some(socket_t fd, int timeout_s, std::byte* out, size_t size) {
    for (;;) {
        const ssize_t n = ::recv(fd, out, size, MSG_DONTWAIT);
        if (n >= 0) return n;
        if (errno == EINTR) continue;
        if (errno != EAGAIN && errno != EWOULDBLOCK) return -1;
        pollfd p{fd, POLLIN, 0};
        const int ready = ::poll(&p, 1, timeout_s * 1000);
        if (ready < 0 && errno == EINTR) continue;
        if (ready <= 0) return -1;
    }
}

}  // namespace

bool ConnectionServer::process_and_close_socket(socket_t sock) {
    struct Serving {
        explicit Serving(socket_t s) { t_connection_socket = s; }
        ~Serving() { t_connection_socket = -1; }
        Serving(const Serving&) = delete;
        Serving& operator=(const Serving&) = delete;
    } serving(sock);
    return kdrt_httplib_serve_connection(this, sock);
}

uint64_t response_body_bytes(const httplib::Response& res) noexcept {
    return res.content_length_ ? res.content_length_ : res.body.size();
}

bool response_has_content(const httplib::Response& res) noexcept {
    return !res.body.empty() || res.content_length_ > 0;
}

void keep_until_sent(httplib::Response& res, std::shared_ptr<void> resource) {
    if (!res.content_provider_) return;
    auto previous = std::move(res.content_provider_resource_releaser_);
    res.content_provider_resource_releaser_ = [resource = std::move(resource),
                                               previous](bool success) {
        if (previous) previous(success);
    };
}

bool read_body_direct(const httplib::Request& req, const httplib::ContentReader& reader,
                      uint64_t direct_bytes, int read_timeout_s,
                      const std::function<bool(std::span<const std::byte>)>& take,
                      const std::function<bool(const SocketReceive&)>& take_rest) {
    const std::optional<uint64_t> declared = declared_body_bytes(req);
    const bool chunked = is_chunked(req);
    if (!(declared && *declared > 0) && !chunked) return true;  // no body to read
    const std::optional<socket_t> socket =
        declared && *declared >= direct_bytes ? direct_socket(req) : std::nullopt;
    uint64_t received = 0;
    bool go_direct = false;
    const bool read_ok = reader([&](const char* data, size_t size) {
        received += size;
        if (!take(std::span(reinterpret_cast<const std::byte*>(data), size))) return false;
        if (socket && received < *declared) {
            go_direct = true;
            return false;  // httplib's reader stops here; take_rest receives the rest
        }
        return true;
    });
    if (!go_direct) return read_ok;
    return take_rest([fd = *socket, read_timeout_s](std::byte* out, size_t size) {
        return receive_some(fd, read_timeout_s, out, size);
    });
}

}  // namespace kdrt::server
