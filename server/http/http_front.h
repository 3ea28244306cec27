#pragma once
/// kdrt's HTTP/1.1 front: owns the listening socket and every client connection, reads request
/// heads (request_head.h) and bodies, and writes responses; the routes see cpp-httplib's
/// Request, Response and ContentReader as plain data types through their public fields and
/// constructors only. See server/README.md "Connections" for why kdrt owns this layer.
/// Included by server/http/*.cpp only.

#include <httplib.h>

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>

#include "kdrt/proto/result.h"

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
    std::atomic<size_t> idle{0};     ///< worker threads free for the next request (started)
    std::atomic<size_t> waiting{0};  ///< complete requests waiting for a worker thread
    /// Requests a worker took from the connection it had just answered, without the event loop
    /// (a count for tests, not exported as a metric).
    std::atomic<uint64_t> taken_after_answer{0};
};

/// Bytes of request bodies the event loop holds, over all connections, while it waits for them
/// to be complete (ConnectionLimits::prebuffer_bytes each); a body that would go beyond this is
/// given a thread at once instead. Request heads are bounded separately, max_head_bytes each.
inline constexpr size_t kPrebufferBudgetBytes = size_t{64} << 20;

/// A request the front answers itself, before any route sees it: 400 or 431 (a head it cannot
/// accept), 408 (head or small body not received in time), 503 (too many
/// connections). Given the status, the request's method token ("" if unknown) and a detail;
/// returns the problem+json body to send (and logs and counts the refusal).
using EarlyReply =
    std::function<std::string(int status, std::string_view method, const std::string& detail)>;

/// Answers one request whose head has arrived: fills `res`. `reader` reads the body (sending
/// `100 Continue` first when the client asked for it, so a route that refuses before reading
/// never invites the body). A body left unread is drained when small, else the connection is
/// closed after the reply. Called on a worker thread; exceptions are the caller's to catch.
using AnswerRequest = std::function<void(httplib::Request& req, httplib::Response& res,
                                         const httplib::ContentReader& reader)>;

/// Called on the same thread once the response is written (or failed to be).
using ResponseSent = std::function<void(const httplib::Request& req, const httplib::Response& res)>;

/// The event-driven front. One epoll loop (on the thread that calls serve()) accepts
/// connections and reads each request's head, and a body up to prebuffer_bytes, without a
/// thread, enforcing the head's size, header count and deadline; a connection waiting for its
/// next request costs no thread. Only a request whose head (and small body) has arrived goes to
/// one of `threads` workers, which calls AnswerRequest and writes the response; further body
/// reads are bounded by the read timeout and the request's deadline. Between requests the
/// connection goes back to the loop; pipelined requests are kept in its buffer. Every response
/// it writes, a route's or its own refusal, carries `X-Content-Type-Options: nosniff` (a route
/// need not, and cannot, set it).
class HttpFront {
public:
    HttpFront(ConnectionLimits limits, EarlyReply early_reply, AnswerRequest answer,
              ResponseSent sent);
    ~HttpFront();
    HttpFront(const HttpFront&) = delete;
    HttpFront& operator=(const HttpFront&) = delete;

    /// Binds and listens on HOST:PORT (port 0: any free port), with SO_REUSEADDR and a backlog
    /// of `backlog`. Returns the bound port, or the reason it failed (errno text).
    [[nodiscard]] proto::Result<int, std::string> bind(const std::string& host, int port,
                                                       int backlog);
    /// Serves until stop(); then answers the requests already received and returns. False if
    /// not bound or the listening socket failed.
    bool serve();
    /// From any thread (also before serve(), which then returns at once).
    void stop();

    /// The live gauges (shared: they outlive the front for a scrape that races its end).
    [[nodiscard]] std::shared_ptr<const ConnectionGauges> gauges() const noexcept;

    struct Impl;

private:
    std::unique_ptr<Impl> impl_;
};

/// True when the request being served on this thread ran out of its request_timeout_s while its
/// body was being read (its reply should be 408; the connection is closed after it).
[[nodiscard]] bool request_deadline_passed() noexcept;

/// A check, callable from any thread while the request being served on this thread is answered,
/// of whether its client has closed the connection (hung up or reset). Outside a front worker
/// it always says no.
[[nodiscard]] std::function<bool()> client_gone_check();

/// The body of the response being answered on this thread, sent from memory the route keeps
/// (no copy): `bytes` must stay valid until the response is written, which `owner` ensures
/// (released once sent or abandoned). Sets the status to 200 and the Content-Type, and empties
/// `res.body`; a body set into `res.body` afterwards (an error reply) replaces it. Outside a
/// front worker the bytes are copied into `res.body`.
void reply_from_memory(httplib::Response& res, std::span<const std::byte> bytes,
                       std::shared_ptr<const void> owner, std::string_view content_type);

/// The response body's size: the memory body's if set (reply_from_memory) and `res.body` is
/// empty, else `res.body`'s.
[[nodiscard]] uint64_t response_body_bytes(const httplib::Response& res) noexcept;

/// Keeps `resource` alive until the response being answered on this thread has been sent or
/// abandoned (a budget hold, an admission slot). Outside a front worker it is released now.
void keep_until_sent(std::shared_ptr<void> resource);

/// The route leaves the request body unread (it refused the request): the front drains a body
/// of known size up to kDrainBodyBytes after the reply, or closes the connection after it (a
/// larger or chunked body, or one whose `100 Continue` was never sent).
void leave_body_unread(httplib::Response& res) noexcept;

/// Receives up to `size` (> 0) bytes of the request body into `out`, like recv(): the count, 0
/// at the body's end or when the peer closed the connection, negative on an error, after the
/// read timeout without data, or once the request's deadline has passed.
using SocketReceive = std::function<ptrdiff_t(std::byte* out, size_t size)>;

/// Reads a request body. A body of at least `direct_bytes` with a Content-Length goes to
/// `take` for what has already arrived (may be nothing) and then to `take_rest`, which receives
/// the remaining bytes straight from the socket into its own storage (large reads, no copy);
/// any other body goes to `take` piece by piece through `reader`. A body without framing is not
/// read. Exactly the body is consumed, so the keep-alive connection stays usable. True when
/// the transport delivered every byte asked for.
[[nodiscard]] bool read_body_direct(const httplib::Request& req,
                                    const httplib::ContentReader& reader, uint64_t direct_bytes,
                                    const std::function<bool(std::span<const std::byte>)>& take,
                                    const std::function<bool(const SocketReceive&)>& take_rest);

}  // namespace kdrt::server
