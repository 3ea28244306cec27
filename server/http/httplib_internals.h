#pragma once
/// Every use of cpp-httplib beyond its documented API, in one place: response fields httplib
/// marks private by convention (content_length_, content_provider_, its resource releaser), the
/// protected Server::process_request and listening socket (the connection layer below), and
/// reading a body past httplib's own buffering. Written against
/// cpp-httplib 0.11.4 (Debian 12's) and checked at compile time: another version fails to build
/// here, so an upgrade is a decision to re-check these, never a silent change of behaviour.
/// Included by server/http_*.cpp only.

#include <httplib.h>

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>

#ifndef CPPHTTPLIB_VERSION
#error "httplib_internals.h: cpp-httplib does not define CPPHTTPLIB_VERSION"
#endif
// The preprocessor cannot compare strings; a static_assert fails the build just as surely.
static_assert(std::string_view(CPPHTTPLIB_VERSION) == "0.11.4",
              "server/httplib_internals.* rely on cpp-httplib 0.11.4 internals: re-check them "
              "(socket access, buffering, private Response fields) before changing the version");
static_assert(CPPHTTPLIB_RECV_BUFSIZ == 4096, "read_body_direct relies on httplib's 4 KiB reads");

namespace kdrt::server {

/// What the connection layer enforces (from ServerConfig; see config/kdrt.json).
struct ConnectionLimits {
    unsigned threads = 32;  ///< threads answering requests
    unsigned keep_alive_timeout_s = 2;
    unsigned keep_alive_max_requests = 1000;
    unsigned read_timeout_s = 30;     ///< one read on a thread, without data
    unsigned write_timeout_s = 30;    ///< one write, without progress
    unsigned head_timeout_s = 10;     ///< first byte of a request to the end of its head
    unsigned request_timeout_s = 60;  ///< first byte of a request to the end of its body
    size_t max_head_bytes = size_t{32} << 10;
    size_t max_headers = 100;
    size_t prebuffer_bytes = size_t{256} << 10;  ///< body bytes read before a thread is given
    size_t max_connections = 4096;
};

/// Gauges of the connection layer (the kdrt_http_* metrics), readable from any thread while the
/// server runs and after it has stopped.
struct ConnectionGauges {
    std::atomic<size_t> open{0};     ///< client connections open (idle, arriving or answered)
    std::atomic<size_t> busy{0};     ///< worker threads answering a request
    std::atomic<size_t> waiting{0};  ///< complete requests waiting for a worker thread
};

/// Bytes of request bodies the poll() loop holds, over all connections, while it waits for them
/// to be complete (ConnectionLimits::prebuffer_bytes each); a body that would go beyond this is
/// given a thread at once instead. Request heads are bounded separately, max_head_bytes each.
inline constexpr size_t kPrebufferBudgetBytes = size_t{64} << 20;

/// A request the connection layer answers itself, before httplib parses it: 408 (head or small
/// body not received in time), 431 (head too large, too many headers), 503 (too many
/// connections). Given the status, the request's method token ("" if unknown) and a detail;
/// returns the problem+json body to send (and logs and counts the refusal).
using EarlyReply =
    std::function<std::string(int status, std::string_view method, const std::string& detail)>;

/// The httplib::Server kdrt serves with. httplib 0.11.4 gives each connection a thread from
/// accept to close: a keep-alive connection pins one while idle, and a client trickling a head or
/// a body (httplib's timeout is per read) pins one indefinitely, so 32 such clients starve every
/// other request. This class keeps httplib's request parsing, routing and response writing
/// (Server::process_request, called once per request) but replaces the connection handling
/// under it: accepted sockets go to one epoll loop, which reads each request's head (and a body
/// up to prebuffer_bytes) without a thread, enforcing the head's size, header count and deadline
/// itself; only a request whose head (and small body) has fully arrived is handed to one of
/// `threads` workers, over a Stream that serves the bytes already read and enforces the whole
/// request's deadline on every further read. Between requests the connection goes back to the
/// loop. Also: pipelined requests are kept (the bytes after one request stay in the connection's
/// buffer), and Range headers are ignored (a ray answer or an image has no use for multipart
/// ranges, and httplib builds them in memory: a 1,000-range request of a 3 MiB image is 3 GiB).
class ConnectionServer : public httplib::Server {
public:
    ConnectionServer();
    ~ConnectionServer() override;
    ConnectionServer(const ConnectionServer&) = delete;
    ConnectionServer& operator=(const ConnectionServer&) = delete;

    /// Before listening. `early_reply` builds the answers the connection layer sends itself.
    void set_connection_limits(const ConnectionLimits& limits, EarlyReply early_reply);

    /// After binding: the listen backlog (httplib 0.11.4 listens with 5).
    bool set_listen_backlog(int backlog);

    /// Open client connections (idle, arriving or being answered).
    [[nodiscard]] size_t open_connections() const noexcept;

    /// The live gauges (shared: they outlive the server for a scrape that races its end).
    [[nodiscard]] std::shared_ptr<const ConnectionGauges> gauges() const noexcept;

    struct Reactor;

private:
    bool process_and_close_socket(socket_t sock) override;
    bool serve_one(httplib::Stream& stream, bool last, bool& closed);

    std::unique_ptr<Reactor> reactor_;
};

/// True when the request being served on this thread ran out of its request_timeout_s while its
/// body was being read (its reply should be 408; the connection is closed after it).
[[nodiscard]] bool request_deadline_passed() noexcept;

/// A check, callable from any thread while the request being served on this thread is answered,
/// of whether its client has closed the connection (hung up or reset). Outside a
/// ConnectionServer's worker it always says no.
[[nodiscard]] std::function<bool()> client_gone_check();

/// Called once a response is written (by the logger): a response with `Connection: close`
/// closes the connection it went out on (httplib 0.11.4 only honours the request's).
void note_response_sent(const httplib::Response& res) noexcept;

/// The response body's size: a content provider's declared length, else the body string's.
[[nodiscard]] uint64_t response_body_bytes(const httplib::Response& res) noexcept;

/// True when the response already has a body (a string or a content provider).
[[nodiscard]] bool response_has_content(const httplib::Response& res) noexcept;

/// A streamed response (content provider) is written after the handler returns: keeps
/// `resource` alive until it has been sent or abandoned. For other responses `resource` is
/// released on return.
void keep_until_sent(httplib::Response& res, std::shared_ptr<void> resource);

/// Receives up to `size` (> 0) bytes into `out`, like recv(): the count, 0 when the peer closed
/// the connection, negative on an error, after the read timeout without data, or once the
/// request's deadline has passed.
using SocketReceive = std::function<ptrdiff_t(std::byte* out, size_t size)>;

/// Reads a request body, handing each piece to `take` (false stops reading). A body without
/// framing (no Content-Length > 0, not chunked) is not read. httplib 0.11.4 hands a streamed body
/// to the handler in 4 KiB pieces, each after a poll() and a recv() into a stack buffer: a 32 MiB
/// ray batch costs 16k system calls and an extra copy. So for a body of at least `direct_bytes`
/// with a Content-Length and no Content-Encoding, only the first piece comes through httplib;
/// httplib's reader is then stopped and `take_rest` receives the remaining bytes from the
/// connection itself (what the connection layer had buffered, then the socket), with large reads
/// into its own storage. Exactly the body is consumed, so the keep-alive connection stays usable.
/// Outside a ConnectionServer's worker the whole body goes through httplib. True when the
/// transport delivered every byte asked for.
[[nodiscard]] bool read_body_direct(const httplib::Request& req,
                                    const httplib::ContentReader& reader, uint64_t direct_bytes,
                                    const std::function<bool(std::span<const std::byte>)>& take,
                                    const std::function<bool(const SocketReceive&)>& take_rest);

}  // namespace kdrt::server
