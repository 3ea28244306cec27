#pragma once
/// Helpers shared by the http/*.cpp files (the only files that see httplib.h): the per-request
/// context used by the access log, problem and body replies, and body reading with limits.

#include <httplib.h>

#include <chrono>
#include <cstdint>
#include <functional>
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

/// True when the request's Content-Type (its essence) is `type`; else replies 415 naming the
/// route (`route`, e.g. "distance"), the type it expects and the one given, and returns false.
[[nodiscard]] bool has_media_type(const httplib::Request& req, httplib::Response& res,
                                  std::string_view type, std::string_view route);

/// The request's query parameters as proto's query parsers read them: a value, or nullopt.
[[nodiscard]] std::function<std::optional<std::string>(std::string_view)> query_params(
    const httplib::Request& req);

/// Replies `status` with a JSON body (moved, not copied).
void reply_json(httplib::Response& res, int status, std::string json);

/// Replies 200 with a binary body; large bodies are sent from the vector itself (no copy,
/// reply_from_memory), which goes back to `pool` (if given) once sent.
void reply_bytes(httplib::Response& res, std::vector<std::byte> bytes,
                 std::string_view content_type, VectorPool<std::byte>* pool = nullptr);

/// Replies 200 with the first `size` bytes of `buffer`: small bodies are copied into the
/// response, large ones are sent from the buffer itself (no copy, reply_from_memory); the buffer
/// goes back to its pool once copied, or once sent or abandoned.
void reply_buffer(httplib::Response& res, PooledBuffer buffer, size_t size,
                  std::string_view content_type);

/// 408 for a body that did not arrive within the request's deadline (request_timeout_s).
[[nodiscard]] proto::Problem body_timeout_problem();

/// Checked as a body arrives, with the bytes received so far: a problem stops reading and is
/// the reply (a budget that does not stretch to the body's size).
using BodyProgress = std::function<std::optional<proto::Problem>(uint64_t received)>;

/// Reads the request body through `reader` into a RequestBody (memory up to `memory_bytes`, then
/// spooled to `spool_dir`). Refuses more than `limit` bytes with 413 (`what` names the body in
/// the detail). Counts the bytes in the request context (bytes_in), once. `progress` (if set)
/// is asked after every piece. On failure the reply is already set and nullptr is returned.
[[nodiscard]] std::unique_ptr<RequestBody> read_body(
    const httplib::Request& req, httplib::Response& res, const httplib::ContentReader& reader,
    uint64_t limit, uint64_t memory_bytes, const std::string& spool_dir, const std::string& what,
    std::vector<std::byte> buffer = {}, const BodyProgress& progress = {});

/// True when the request body is framed as chunks (Transfer-Encoding: chunked).
[[nodiscard]] bool is_chunked(const httplib::Request& req);

/// The body's size declared in advance: Content-Length, unless the body is chunked or has none.
[[nodiscard]] std::optional<uint64_t> declared_body_bytes(const httplib::Request& req);

/// The body as text (for JSON decoders).
[[nodiscard]] inline std::string_view as_text(std::span<const std::byte> bytes) noexcept {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

}  // namespace kdrt::server
