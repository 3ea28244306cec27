#pragma once
/// The client's one way around cpp-httplib: ray batches, synchronous renders and job results over
/// plain http (the large bodies) go through a keep-alive HTTP/1.1 connection of this file's own.
/// cpp-httplib 0.11.4 (Debian 12's, a compiled shared library) reads every response body in 4 KiB
/// pieces, each after a poll() (its CPPHTTPLIB_RECV_BUFSIZ is fixed when the library is built): a
/// 16 MiB KDRH answer costs 8k system call pairs, and the client reached half of the server's rate.
/// Here a request goes out as one sendmsg() of the head and the caller's body, and the answer is
/// read with large recv() calls straight into a reused buffer. Everything else (JSON calls,
/// uploads, job submissions, https) stays on httplib's public API in http_client.cpp; this file
/// includes no httplib header and touches none of its internals. Retries, backoff and problem+json
/// errors stay in http_client.cpp, which maps DirectFailure onto the same messages as httplib's
/// errors.

#include <chrono>
#include <cstddef>
#include <memory>
#include <span>
#include <string>
#include <string_view>

namespace kdrt::detail {

/// Why an exchange failed at the transport level (none of these is an HTTP status).
enum class DirectFailure {
    kNone,
    kConnect,         ///< the TCP connection could not be set up (refused, unreachable, no host)
    kConnectTimeout,  ///< nor within the connect timeout
    kWrite,           ///< the connection closed or timed out while the request was sent
    kRead,            ///< the connection closed or timed out before the whole answer arrived
    kProtocol,        ///< the answer is not HTTP/1.x this reader understands (detail says why)
};

/// One answer: status, the headers the client uses, and the body in a buffer reused by the next
/// exchange on the same connection.
struct DirectResponse {
    int status = 0;
    std::string content_type;
    std::string retry_after;
    std::string request_id;
    std::string replica;          ///< X-Kdrt-Replica (docs/scale-out.md)
    std::string png_compression;  ///< X-Kdrt-Png-Compression (raw renders)
    /// The body: body()[0, size). Valid until the next exchange on the connection.
    [[nodiscard]] std::span<const std::byte> body() const noexcept { return {data_.get(), size_}; }

    /// Room for `size` body bytes (contents kept up to the old size); never shrinks.
    std::byte* reserve(size_t size);
    void set_size(size_t size) noexcept { size_ = size; }

private:
    std::unique_ptr<std::byte[]> data_;
    size_t size_ = 0;
    size_t capacity_ = 0;
};

/// Where and how to connect.
struct DirectTarget {
    std::string host;  ///< a name or a numeric address, IPv6 without brackets
    int port = 80;
    std::string host_header;  ///< the Host header's value ("host:port", IPv6 in brackets)
    std::string token;        ///< bearer token, or empty
    std::chrono::milliseconds connect_timeout{5'000};
    std::chrono::milliseconds io_timeout{300'000};  ///< per send/receive, as httplib's timeouts
};

/// A keep-alive HTTP/1.1 connection, opened lazily and reopened when the server closed it. Not
/// thread-safe: one exchange at a time (kdrt::Client gives each chunk worker its own).
class DirectConnection {
public:
    explicit DirectConnection(DirectTarget target);
    ~DirectConnection();
    DirectConnection(const DirectConnection&) = delete;
    DirectConnection& operator=(const DirectConnection&) = delete;

    /// Sends `method` `path` with `body` (Content-Type `content_type`, none when empty; a
    /// Content-Length for a POST or a non-empty body) and reads the whole answer into
    /// `response`. For idempotent requests only (see below). A body larger than `max_body` bytes is
    /// refused as kProtocol before it is read (the connection is then closed). A connection kept
    /// alive from an earlier exchange that turns out closed by the server before any byte of the
    /// answer arrived is reopened and the request sent once more (the server never saw it), as
    /// browsers do; every other failure is returned, with `detail` naming it (an OS error text, or
    /// what was wrong with the answer).
    [[nodiscard]] DirectFailure request(std::string_view method, std::string_view path,
                                        std::string_view content_type,
                                        std::span<const std::byte> body, size_t max_body,
                                        DirectResponse& response, std::string& detail);

private:
    DirectFailure exchange(std::string_view head, std::span<const std::byte> body, size_t max_body,
                           DirectResponse& response, std::string& detail, bool& nothing_received);
    DirectFailure connect(std::string& detail);
    void close() noexcept;

    DirectTarget target_;
    int fd_ = -1;
    std::string buffered_;  ///< bytes received past the end of the headers being parsed
};

}  // namespace kdrt::detail
