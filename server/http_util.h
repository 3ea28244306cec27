#pragma once
/// Helpers shared by the http_*.cpp files (the only files that see httplib.h): the per-request
/// context used by the access log, problem and body replies, and body reading with limits.

#include <httplib.h>

#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "buffer_pool.h"
#include "kdrt/proto/problem.h"
#include "request_body.h"

namespace kdrt::server {

/// What the access log and metrics need to know about the request being served on this thread.
/// Set by the pre-routing handler and the route wrapper, read by the logger after the response
/// is written (httplib serves a request on one thread from start to finish).
struct RequestContext {
    std::chrono::steady_clock::time_point start;
    bool active = false;
    std::string route;       ///< route template, e.g. "/v1/meshes/{id}/intersect"
    std::string request_id;  ///< also sent as X-Request-Id
    uint64_t bytes_in = 0;   ///< body bytes received (streamed routes)
    uint64_t rays = 0;
};

/// The context of the request this thread is serving.
[[nodiscard]] RequestContext& request_context() noexcept;

/// Replies with `problem` as application/problem+json (status from its kind), filling instance
/// and request_id, and Retry-After when set.
void reply_problem(const httplib::Request& req, httplib::Response& res, proto::Problem problem);

/// Replies `status` with a JSON body (moved, not copied).
void reply_json(httplib::Response& res, int status, std::string json);

/// Replies 200 with a binary body; large bodies are streamed from memory by a content provider,
/// and their vector goes back to `pool` (if given) once sent.
void reply_bytes(httplib::Response& res, std::vector<std::byte> bytes,
                 std::string_view content_type, VectorPool<std::byte>* pool = nullptr);

/// Replies 200 with the first `size` bytes of `buffer`: small bodies are copied into the
/// response, large ones are streamed from the buffer itself by a content provider (no copy) and
/// the buffer goes back to `pool` (if given) once sent or abandoned.
void reply_buffer(httplib::Response& res, AlignedBuffer buffer, size_t size,
                  std::string_view content_type, BufferPool* pool = nullptr);

/// After an early error reply on a streamed route, the body has not been read: drain it if it
/// is small, else ask the client to close the connection (never parse it as the next request).
void discard_body(const httplib::Request& req, httplib::Response& res,
                  const httplib::ContentReader& reader);

/// Reads the request body through `reader` into a RequestBody (memory up to `memory_bytes`, then
/// spooled to `spool_dir`). Refuses more than `limit` bytes with 413 (`what` names the body in
/// the detail). On failure the reply is already set and nullptr is returned.
[[nodiscard]] std::unique_ptr<RequestBody> read_body(
    const httplib::Request& req, httplib::Response& res, const httplib::ContentReader& reader,
    uint64_t limit, uint64_t memory_bytes, const std::string& spool_dir, const std::string& what,
    std::vector<std::byte> buffer = {});

/// Reading a large body past cpp-httplib. httplib 0.11.4 hands a streamed body to the handler in
/// 4 KiB pieces, each after a poll() and a recv() into a stack buffer: a 32 MiB ray batch costs
/// 16k system calls and an extra copy. Instead, the route takes the first piece from httplib
/// (which drains whatever httplib had buffered after the headers: its buffer holds one recv()
/// of at most 4 KiB and a 4 KiB read request empties it), stops httplib's reader, and receives
/// the rest of the body from the connection's socket straight into its own storage with large
/// reads. The connection stays usable for keep-alive: exactly the body is consumed, and httplib
/// reads the next request from the socket as usual. Only for bodies with a Content-Length and no
/// Content-Encoding, and only on the httplib version this was checked against; anywhere else
/// (or if the socket cannot be identified) the route reads through httplib as before.
struct DirectBody {
    int fd = -1;         ///< the connection's socket
    int timeout_s = 30;  ///< per read, like httplib's read timeout
};

/// The socket `req` arrived on, when the body may be read from it directly (see DirectBody):
/// nullopt when it may not or the socket cannot be identified for certain.
[[nodiscard]] std::optional<DirectBody> direct_body(const httplib::Request& req,
                                                    int read_timeout_s);

/// Receives up to `size` bytes (at least 1) from the socket into `out`. Returns the count, 0 when
/// the peer closed the connection, -1 on an error or after timeout_s without data.
[[nodiscard]] ssize_t receive_some(const DirectBody& body, std::byte* out, size_t size);

/// The body as text (for JSON decoders).
[[nodiscard]] inline std::string_view as_text(std::span<const std::byte> bytes) noexcept {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

}  // namespace kdrt::server
