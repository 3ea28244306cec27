#pragma once
/// Every use of cpp-httplib beyond its documented API, in one place: response fields httplib
/// marks private by convention (content_length_, content_provider_, its resource releaser), the
/// connection's socket, and reading a body past httplib's own buffering. Written against
/// cpp-httplib 0.11.4 (Debian 12's) and checked at compile time: another version fails to build
/// here, so an upgrade is a decision to re-check these, never a silent change of behaviour.
/// Included by server/http_*.cpp only.

#include <httplib.h>

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>

#ifndef CPPHTTPLIB_VERSION
#error "httplib_internals.h: cpp-httplib does not define CPPHTTPLIB_VERSION"
#endif
// The preprocessor cannot compare strings; a static_assert fails the build just as surely.
static_assert(std::string_view(CPPHTTPLIB_VERSION) == "0.11.4",
              "server/httplib_internals.* rely on cpp-httplib 0.11.4 internals: re-check them "
              "(socket access, buffering, private Response fields) before changing the version");
static_assert(CPPHTTPLIB_RECV_BUFSIZ == 4096, "read_body_direct relies on httplib's 4 KiB reads");

namespace kdrt::server {

/// The httplib::Server kdrt serves with: it also remembers, on the thread serving a connection,
/// that connection's socket, for read_body_direct(). httplib 0.11.4 gives handlers neither the
/// connection's Stream nor its socket; the only place that sees the accepted socket is the
/// private virtual Server::process_and_close_socket, which this class overrides.
class ConnectionServer : public httplib::Server {
private:
    bool process_and_close_socket(socket_t sock) override;
};

/// The response body's size: a content provider's declared length, else the body string's.
[[nodiscard]] uint64_t response_body_bytes(const httplib::Response& res) noexcept;

/// True when the response already has a body (a string or a content provider).
[[nodiscard]] bool response_has_content(const httplib::Response& res) noexcept;

/// A streamed response (content provider) is written after the handler returns: keeps
/// `resource` alive until it has been sent or abandoned. For other responses `resource` is
/// released on return.
void keep_until_sent(httplib::Response& res, std::shared_ptr<void> resource);

/// Receives up to `size` (> 0) bytes into `out`, like recv(): the count, 0 when the peer closed
/// the connection, negative on an error or after the read timeout without data.
using SocketReceive = std::function<ptrdiff_t(std::byte* out, size_t size)>;

/// Reads a request body, handing each piece to `take` (false stops reading). A body without
/// framing (no Content-Length > 0, not chunked) is not read. httplib 0.11.4 hands a streamed body
/// to the handler in 4 KiB pieces, each after a poll() and a recv() into a stack buffer: a 32 MiB
/// ray batch costs 16k system calls and an extra copy. So for a body of at least `direct_bytes`
/// with a Content-Length and no Content-Encoding, only the first piece comes through httplib
/// (which drains whatever httplib had buffered after the headers: its buffer holds one recv() of
/// at most 4 KiB and a 4 KiB read request empties it); httplib's reader is then stopped and
/// `take_rest` receives the remaining bytes from the connection's socket itself, with large reads
/// into its own storage. Exactly the body is consumed, so the keep-alive connection stays usable.
/// If the socket cannot be identified for certain, the whole body goes through httplib. True
/// when the transport delivered every byte asked for.
[[nodiscard]] bool read_body_direct(const httplib::Request& req,
                                    const httplib::ContentReader& reader, uint64_t direct_bytes,
                                    int read_timeout_s,
                                    const std::function<bool(std::span<const std::byte>)>& take,
                                    const std::function<bool(const SocketReceive&)>& take_rest);

}  // namespace kdrt::server
