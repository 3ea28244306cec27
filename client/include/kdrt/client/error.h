#pragma once
/// Errors of the kdrt client library: what the server said (RFC 9457 problem details, see
/// kdrt/proto/problem.h) or why no usable answer arrived. Every Client call returns a
/// kdrt::Result<T> (a proto::Result<T, kdrt::Error>); nothing in the library throws except
/// std::bad_alloc and the Client constructor's std::invalid_argument for a malformed URL.

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "kdrt/proto/result.h"

namespace kdrt {

/// Why a call failed.
enum class ErrorKind {
    kServer,  ///< the server answered with an error status (4xx/5xx); status/title/detail are its
    kConnection,  ///< no answer: cannot connect, connection lost, or timed out (after the retries)
    kProtocol,    ///< the server answered 2xx with a body the API does not allow (bad JSON/KDRH,
                  ///< count)
    kInput,  ///< a local input is unusable: unreadable file, unknown mesh format, > 2^32 - 1 rays
    kJobFailed,  ///< a render job ended in state "failed" (detail: the server's reason)
    kCancelled,  ///< a render job was cancelled (by cancel(), the server, or a progress callback)
};

/// "server", "connection", "protocol", "input", "job_failed", "cancelled".
[[nodiscard]] std::string_view error_kind_name(ErrorKind kind) noexcept;

/// A failed call. For kServer the fields come from the problem+json body (title from its type,
/// e.g. "Unknown mesh"); a body that is not problem+json gives the HTTP reason phrase as title and
/// the start of the body as detail. For the other kinds `title` is a short fixed phrase
/// ("cannot connect", "bad response", ...) and `detail` names the URL, file or value.
struct Error {
    ErrorKind kind = ErrorKind::kServer;
    int status = 0;  ///< HTTP status (kServer; also kProtocol), else 0
    std::string title;
    std::string detail;
    std::string type;              ///< problem type URN ("urn:kdrt:problem:unknown-mesh"), or empty
    std::string code;              ///< problem `code` (e.g. "bad_magic"), or empty
    std::string request_id;        ///< problem request_id / X-Request-Id, or empty
    std::optional<uint64_t> line;  ///< mesh parse errors in text: 1-based line
    std::optional<uint64_t> byte_offset;  ///< mesh parse errors in binary data
    std::optional<uint64_t> limit;        ///< the server limit that was exceeded
    /// The request member a problem names ("instances[3].transform", "If-Match"), or empty.
    std::string field;
    std::optional<uint32_t> index;        ///< the instance (or pose entry) index a problem names
    std::optional<uint32_t> retry_after;  ///< seconds (503)
    unsigned attempts = 1;                ///< requests sent for this call: 1 + retries

    /// One line: "404 Unknown mesh: no mesh with id 3f2a..." for kServer, "<title>: <detail>"
    /// otherwise (e.g. "cannot connect: http://127.0.0.1:1: Could not establish connection
    /// (5 attempts)").
    [[nodiscard]] std::string to_string() const;
};

/// A value of type T, or an Error.
template <class T>
using Result = proto::Result<T, Error>;

/// The Error of an HTTP answer with a non-2xx `status`. A problem+json body (by Content-Type, or
/// any body that decodes as one) fills title, detail, type, code, line, byte_offset, limit,
/// field, index, retry_after and request_id; any other body becomes the detail (its first 300
/// bytes, control characters as spaces) with the reason phrase of `status` as title.
/// `request_id` (the X-Request-Id header) is used when the body has none. Thread-safe.
[[nodiscard]] Error error_from_response(int status, std::string_view content_type,
                                        std::string_view body, std::string_view request_id = {});

/// An Error of a local `kind` (not kServer) with the given title and detail.
[[nodiscard]] Error make_client_error(ErrorKind kind, std::string title, std::string detail);

}  // namespace kdrt
