#include "http_direct.h"

#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <sys/uio.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cstring>
#include <optional>

namespace kdrt::detail {
namespace {

/// Receive size for the header part and for chunked bodies.
constexpr size_t kReadBlock = size_t{64} << 10;
/// Longest status line plus headers accepted (the server's are a few hundred bytes).
constexpr size_t kMaxHeadBytes = size_t{64} << 10;

timeval to_timeval(std::chrono::milliseconds ms) noexcept {
    timeval tv{};
    tv.tv_sec = static_cast<time_t>(ms.count() / 1000);
    tv.tv_usec = static_cast<suseconds_t>((ms.count() % 1000) * 1000);
    return tv;
}

std::string os_error(int error) { return std::strerror(error); }

bool iequals(std::string_view a, std::string_view b) noexcept {
    return a.size() == b.size() && std::equal(a.begin(), a.end(), b.begin(), [](char x, char y) {
               return std::tolower(static_cast<unsigned char>(x)) ==
                      std::tolower(static_cast<unsigned char>(y));
           });
}

std::string_view trim(std::string_view s) noexcept {
    while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) s.remove_prefix(1);
    while (!s.empty() && (s.back() == ' ' || s.back() == '\t' || s.back() == '\r'))
        s.remove_suffix(1);
    return s;
}

/// True when the token list `value` (comma-separated, any case) holds `token`.
bool has_token(std::string_view value, std::string_view token) noexcept {
    while (!value.empty()) {
        const size_t comma = value.find(',');
        if (iequals(trim(value.substr(0, comma)), token)) return true;
        if (comma == std::string_view::npos) break;
        value.remove_prefix(comma + 1);
    }
    return false;
}

/// The parsed status line and headers of one answer.
struct Head {
    int status = 0;
    bool http10 = false;
    std::optional<uint64_t> content_length;
    bool chunked = false;
    bool close = false;  ///< Connection: close (or HTTP/1.0 without keep-alive)
    std::string content_type, retry_after, request_id, replica, png_compression;
};

/// Parses "HTTP/1.x SSS reason\r\n(name: value\r\n)*" (the blank line excluded). Empty on
/// success, else what is wrong.
std::string parse_head(std::string_view text, Head& head) {
    const size_t eol = text.find("\r\n");
    const std::string_view status_line = text.substr(0, eol);
    if (status_line.size() < 12 || status_line.substr(0, 7) != "HTTP/1." || status_line[8] != ' ')
        return "the answer does not start with an HTTP/1.x status line";
    head.http10 = status_line[7] == '0';
    const auto [ptr, ec] =
        std::from_chars(status_line.data() + 9, status_line.data() + 12, head.status);
    // RFC 9112: three digits, then a space (the reason may be empty); RFC 9110: 100-599.
    if (ec != std::errc() || ptr != status_line.data() + 12 || head.status < 100 ||
        head.status > 599 || (status_line.size() > 12 && status_line[12] != ' '))
        return "bad status in \"" + std::string(status_line.substr(0, 40)) + "\"";
    bool keep_alive = false;
    text = eol == std::string_view::npos ? std::string_view() : text.substr(eol + 2);
    while (!text.empty()) {
        const size_t end = text.find("\r\n");
        const std::string_view line = text.substr(0, end);
        text = end == std::string_view::npos ? std::string_view() : text.substr(end + 2);
        const size_t colon = line.find(':');
        if (colon == std::string_view::npos || colon == 0)
            return "malformed header line \"" + std::string(line.substr(0, 60)) + "\"";
        const std::string_view name = line.substr(0, colon), value = trim(line.substr(colon + 1));
        if (iequals(name, "Content-Length")) {
            uint64_t length = 0;
            const auto [p, e] = std::from_chars(value.data(), value.data() + value.size(), length);
            if (e != std::errc() || p != value.data() + value.size())
                return "bad Content-Length \"" + std::string(value.substr(0, 30)) + "\"";
            if (head.content_length && *head.content_length != length)
                return "two different Content-Length headers";
            head.content_length = length;
        } else if (iequals(name, "Transfer-Encoding")) {
            if (!has_token(value, "chunked"))
                return "unsupported Transfer-Encoding \"" + std::string(value.substr(0, 30)) + "\"";
            head.chunked = true;
        } else if (iequals(name, "Connection")) {
            if (has_token(value, "close")) head.close = true;
            if (has_token(value, "keep-alive")) keep_alive = true;
        } else if (iequals(name, "Content-Type")) {
            head.content_type = value;
        } else if (iequals(name, "Retry-After")) {
            head.retry_after = value;
        } else if (iequals(name, "X-Request-Id")) {
            head.request_id = value;
        } else if (iequals(name, "X-Kdrt-Replica")) {
            head.replica = value;
        } else if (iequals(name, "X-Kdrt-Png-Compression")) {
            head.png_compression = value;
        }
    }
    if (head.http10 && !keep_alive) head.close = true;
    return {};
}

}  // namespace

std::byte* DirectResponse::reserve(size_t size) {
    if (size > capacity_) {
        // Grow geometrically, so answers of slowly rising size do not reallocate every time.
        const size_t capacity = std::max(size, capacity_ + capacity_ / 2);
        auto grown = std::make_unique_for_overwrite<std::byte[]>(capacity);
        if (size_ > 0) std::memcpy(grown.get(), data_.get(), size_);
        data_ = std::move(grown);
        capacity_ = capacity;
    }
    return data_.get();
}

DirectConnection::DirectConnection(DirectTarget target) : target_(std::move(target)) {}

DirectConnection::~DirectConnection() { close(); }

void DirectConnection::close() noexcept {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
    buffered_.clear();
}

DirectFailure DirectConnection::connect(std::string& detail) {
    addrinfo hints{};
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    addrinfo* found = nullptr;
    const std::string service = std::to_string(target_.port);
    if (const int rc = ::getaddrinfo(target_.host.c_str(), service.c_str(), &hints, &found);
        rc != 0) {
        detail = rc == EAI_SYSTEM ? os_error(errno) : ::gai_strerror(rc);
        return DirectFailure::kConnect;
    }
    DirectFailure failure = DirectFailure::kConnect;
    for (const addrinfo* ai = found; ai && fd_ < 0; ai = ai->ai_next) {
        const int fd = ::socket(ai->ai_family, ai->ai_socktype | SOCK_CLOEXEC | SOCK_NONBLOCK,
                                ai->ai_protocol);
        if (fd < 0) {
            detail = os_error(errno);
            continue;
        }
        int error = 0;
        if (::connect(fd, ai->ai_addr, ai->ai_addrlen) != 0) {
            error = errno;
            if (error == EINPROGRESS) {
                pollfd p{fd, POLLOUT, 0};
                int ready = 0;
                do {
                    ready = ::poll(&p, 1, static_cast<int>(target_.connect_timeout.count()));
                } while (ready < 0 && errno == EINTR);
                if (ready == 0) {
                    error = ETIMEDOUT;
                } else {
                    socklen_t len = sizeof error;
                    if (::getsockopt(fd, SOL_SOCKET, SO_ERROR, &error, &len) != 0) error = errno;
                }
            }
        }
        if (error != 0) {
            detail = os_error(error);
            failure = error == ETIMEDOUT ? DirectFailure::kConnectTimeout : DirectFailure::kConnect;
            ::close(fd);
            continue;
        }
        // Blocking from here on, each send and receive bounded by the I/O timeout.
        ::fcntl(fd, F_SETFL, ::fcntl(fd, F_GETFL) & ~O_NONBLOCK);
        const int one = 1;
        ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
        const timeval tv = to_timeval(target_.io_timeout);
        ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
        ::setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &tv, sizeof tv);
        fd_ = fd;
    }
    ::freeaddrinfo(found);
    return fd_ >= 0 ? DirectFailure::kNone : failure;
}

DirectFailure DirectConnection::request(std::string_view method, std::string_view path,
                                        std::string_view content_type,
                                        std::span<const std::byte> body, size_t max_body,
                                        DirectResponse& response, std::string& detail) {
    detail.clear();
    if (fd_ >= 0) {
        // An idle keep-alive connection the server has closed (its keep-alive timeout) reads as
        // EOF; anything readable before a request was sent means the connection is not usable.
        pollfd idle{fd_, POLLIN | POLLRDHUP, 0};
        if (::poll(&idle, 1, 0) != 0) close();
    }
    const bool reused = fd_ >= 0;
    if (!reused) {
        if (const DirectFailure f = connect(detail); f != DirectFailure::kNone) return f;
    }
    std::string head;
    head.reserve(256 + path.size() + target_.token.size());
    head.append(method).append(" ").append(path).append(" HTTP/1.1\r\nHost: ");
    head.append(target_.host_header);
    if (!content_type.empty()) head.append("\r\nContent-Type: ").append(content_type);
    if (method == "POST" || !body.empty())
        head.append("\r\nContent-Length: ").append(std::to_string(body.size()));
    head.append("\r\nAccept: */*\r\nConnection: keep-alive\r\nUser-Agent: kdrt-client");
    if (!target_.token.empty()) head.append("\r\nAuthorization: Bearer ").append(target_.token);
    head.append("\r\n\r\n");

    bool nothing_received = false;
    DirectFailure f = exchange(head, body, max_body, response, detail, nothing_received);
    if (f != DirectFailure::kNone && reused && nothing_received &&
        (f == DirectFailure::kWrite || f == DirectFailure::kRead)) {
        // The server closed the kept-alive connection as the request went out; it saw nothing.
        close();
        detail.clear();
        f = connect(detail);
        if (f == DirectFailure::kNone)
            f = exchange(head, body, max_body, response, detail, nothing_received);
    }
    if (f != DirectFailure::kNone) close();
    return f;
}

DirectFailure DirectConnection::exchange(std::string_view head, std::span<const std::byte> body,
                                         size_t max_body, DirectResponse& response,
                                         std::string& detail, bool& nothing_received) {
    nothing_received = true;
    buffered_.clear();
    // The head and the body in one system call (more only for partial writes).
    iovec parts[2] = {{const_cast<char*>(head.data()), head.size()},
                      {const_cast<std::byte*>(body.data()), body.size()}};
    size_t first = 0;
    while (first < 2) {
        msghdr msg{};
        msg.msg_iov = parts + first;
        msg.msg_iovlen = 2 - first;
        const ssize_t n = ::sendmsg(fd_, &msg, MSG_NOSIGNAL);
        if (n < 0) {
            if (errno == EINTR) continue;
            detail =
                errno == EAGAIN || errno == EWOULDBLOCK ? os_error(ETIMEDOUT) : os_error(errno);
            return DirectFailure::kWrite;
        }
        auto sent = static_cast<size_t>(n);
        while (first < 2 && sent >= parts[first].iov_len) {
            sent -= parts[first].iov_len;
            ++first;
        }
        if (first < 2) {
            parts[first].iov_base = static_cast<char*>(parts[first].iov_base) + sent;
            parts[first].iov_len -= sent;
        }
    }

    // Receives into `out`; the count, or a failure (0 bytes = the peer closed).
    const auto receive = [this, &detail](void* out, size_t size) -> ptrdiff_t {
        for (;;) {
            const ssize_t n = ::recv(fd_, out, size, 0);
            if (n >= 0) {
                if (n == 0) detail = "the server closed the connection";
                return n;
            }
            if (errno == EINTR) continue;
            detail =
                errno == EAGAIN || errno == EWOULDBLOCK ? os_error(ETIMEDOUT) : os_error(errno);
            return -1;
        }
    };
    // Ensures buffered_ holds at least `size` bytes.
    const auto fill = [&](size_t size) -> bool {
        while (buffered_.size() < size) {
            const size_t old = buffered_.size();
            buffered_.resize(old + kReadBlock);
            const ptrdiff_t n = receive(buffered_.data() + old, kReadBlock);
            buffered_.resize(old + static_cast<size_t>(std::max<ptrdiff_t>(n, 0)));
            if (n <= 0) return false;
            nothing_received = false;
        }
        return true;
    };

    Head parsed;
    for (;;) {  // 1xx answers are skipped
        size_t end = std::string::npos;
        while ((end = buffered_.find("\r\n\r\n")) == std::string::npos) {
            if (buffered_.size() > kMaxHeadBytes) {
                detail = "the answer's headers exceed " + std::to_string(kMaxHeadBytes) + " bytes";
                return DirectFailure::kProtocol;
            }
            if (!fill(buffered_.size() + 1)) return DirectFailure::kRead;
        }
        parsed = Head{};
        if (std::string error = parse_head(std::string_view(buffered_).substr(0, end), parsed);
            !error.empty()) {
            detail = std::move(error);
            return DirectFailure::kProtocol;
        }
        buffered_.erase(0, end + 4);
        if (parsed.status >= 200) break;
    }
    response.status = parsed.status;
    response.content_type = std::move(parsed.content_type);
    response.retry_after = std::move(parsed.retry_after);
    response.request_id = std::move(parsed.request_id);
    response.replica = std::move(parsed.replica);
    response.png_compression = std::move(parsed.png_compression);
    response.set_size(0);

    bool close_after = parsed.close;
    if (parsed.chunked) {
        size_t size = 0, at = 0;
        for (;;) {
            size_t eol = std::string::npos;
            while ((eol = buffered_.find("\r\n", at)) == std::string::npos) {
                if (buffered_.size() - at > 1024) {
                    detail = "malformed chunk size line";
                    return DirectFailure::kProtocol;
                }
                if (!fill(buffered_.size() + 1)) return DirectFailure::kRead;
            }
            const std::string_view line = std::string_view(buffered_).substr(at, eol - at);
            uint64_t chunk = 0;
            const auto [p, e] = std::from_chars(line.data(), line.data() + line.size(), chunk, 16);
            if (e != std::errc() || p == line.data() ||
                (p != line.data() + line.size() && *p != ';')) {
                detail = "malformed chunk size line";
                return DirectFailure::kProtocol;
            }
            at = eol + 2;
            if (chunk == 0) break;
            if (chunk > max_body - size) {
                detail = "the answer is larger than " + std::to_string(max_body) + " bytes";
                return DirectFailure::kProtocol;
            }
            if (!fill(at + chunk + 2)) return DirectFailure::kRead;
            std::memcpy(response.reserve(size + chunk) + size, buffered_.data() + at, chunk);
            size += chunk;
            response.set_size(size);
            at += chunk + 2;
            buffered_.erase(0, at);  // keeps the buffer one chunk long
            at = 0;
        }
        // Trailers, up to the blank line.
        for (;;) {
            size_t eol = std::string::npos;
            while ((eol = buffered_.find("\r\n", at)) == std::string::npos) {
                if (buffered_.size() > kMaxHeadBytes) {
                    detail =
                        "the answer's trailers exceed " + std::to_string(kMaxHeadBytes) + " bytes";
                    return DirectFailure::kProtocol;
                }
                if (!fill(buffered_.size() + 1)) return DirectFailure::kRead;
            }
            const bool blank = eol == at;
            at = eol + 2;
            if (blank) break;
        }
        buffered_.erase(0, at);
    } else if (parsed.content_length) {
        const uint64_t length = *parsed.content_length;
        if (length > max_body) {
            detail = "the answer's Content-Length " + std::to_string(length) + " is larger than " +
                     std::to_string(max_body) + " bytes";
            return DirectFailure::kProtocol;
        }
        const auto size = static_cast<size_t>(length);
        std::byte* out = response.reserve(size);
        size_t got = std::min(size, buffered_.size());
        if (got > 0) std::memcpy(out, buffered_.data(), got);  // out is null for an empty body
        buffered_.erase(0, got);
        while (got < size) {  // big reads straight into the answer's buffer
            const ptrdiff_t n = receive(out + got, size - got);
            if (n <= 0) return DirectFailure::kRead;
            got += static_cast<size_t>(n);
        }
        response.set_size(size);
    } else {
        // No framing: the body runs to the end of the connection.
        close_after = true;
        size_t size = buffered_.size();
        if (size > max_body) {
            detail = "the answer is larger than " + std::to_string(max_body) + " bytes";
            return DirectFailure::kProtocol;
        }
        if (size > 0) std::memcpy(response.reserve(size), buffered_.data(), size);
        response.set_size(size);  // reserve() keeps the first size() bytes when it grows
        buffered_.clear();
        for (;;) {
            std::byte* out = response.reserve(size + kReadBlock);
            const ptrdiff_t n = receive(out + size, kReadBlock);
            if (n < 0) return DirectFailure::kRead;
            if (n == 0) break;
            size += static_cast<size_t>(n);
            response.set_size(size);
            if (size > max_body) {
                detail = "the answer is larger than " + std::to_string(max_body) + " bytes";
                return DirectFailure::kProtocol;
            }
        }
    }
    // Bytes past the answer were never asked for: the connection is not reused.
    if (close_after || !buffered_.empty()) close();
    return DirectFailure::kNone;
}

}  // namespace kdrt::detail
