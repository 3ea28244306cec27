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

#include "core/buffer_pool.h"
#include "http/request_body.h"
#include "kdrt/proto/problem.h"

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
/// response, large ones are streamed from the buffer itself by a content provider (no copy); the
/// buffer goes back to its pool once copied, or once sent or abandoned.
void reply_buffer(httplib::Response& res, PooledBuffer buffer, size_t size,
                  std::string_view content_type);

/// 408 for a body that did not arrive within the request's deadline (request_timeout_s).
[[nodiscard]] proto::Problem body_timeout_problem();

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

/// True when the request body is framed as chunks (Transfer-Encoding: chunked).
[[nodiscard]] bool is_chunked(const httplib::Request& req);

/// The body's size declared in advance: Content-Length, unless the body is chunked or has none.
[[nodiscard]] std::optional<uint64_t> declared_body_bytes(const httplib::Request& req);

/// The body as text (for JSON decoders).
[[nodiscard]] inline std::string_view as_text(std::span<const std::byte> bytes) noexcept {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

}  // namespace kdrt::server
