#pragma once
/// RFC 9457 problem details (`application/problem+json`): the body of every kdrt API error.
///
///   {"type": "urn:kdrt:problem:unknown-mesh", "title": "Unknown mesh", "status": 404,
///    "detail": "no mesh with id 3f2a...", "instance": "/v1/meshes/3f2a.../intersect",
///    "request_id": "0000000000000007"}
///
/// `type` is a stable URN per ProblemKind (clients branch on it, or on `status`); `detail` is
/// the human-readable, request-specific explanation. Optional extension members: `code` (a
/// machine-readable sub-reason such as the ray-batch DecodeErrorCode name `bad_magic`), `line`
/// and `byte_offset` (where a mesh file is wrong), `field` and `index` (the member and the
/// instance or entry of a scene request that is wrong), `request_id`, `retry_after` (seconds, also
/// sent as the Retry-After header) and `limit` (the limit that was exceeded).

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "kdrt/proto/result.h"

namespace kdrt::proto {

inline constexpr std::string_view kProblemMediaType = "application/problem+json";

/// Every kind of error the API reports. The HTTP status and title are fixed per kind.
enum class ProblemKind {
    kBadRequest,            ///< 400 malformed JSON, parameter or header
    kBadRayBatch,           ///< 400 malformed KDRR body (code = DecodeErrorCode name)
    kUnauthorized,          ///< 401 missing or wrong bearer token
    kForbidden,             ///< 403 valid token without the route's role (code = the role)
    kNotFound,              ///< 404 no such route
    kUnknownMesh,           ///< 404 no mesh with that id
    kUnknownJob,            ///< 404 no job with that id
    kMethodNotAllowed,      ///< 405 route exists, method does not
    kRequestTimeout,        ///< 408 request head or body not received within its deadline
    kJobNotDone,            ///< 409 job result requested before the job succeeded
    kPayloadTooLarge,       ///< 413 body or batch over a configured limit
    kUnsupportedMediaType,  ///< 415 Content-Type (or ?format) not accepted by the route
    kHeadersTooLarge,       ///< 431 request head over its size or header-count limit
    kMeshParseError,        ///< 422 mesh file refused by the parser (line / byte_offset)
    kInvalidMesh,           ///< 422 mesh parsed but cannot be built (e.g. no triangles)
    kInternal,              ///< 500 unexpected failure (logged with request_id)
    kOverCapacity,          ///< 503 too many requests or jobs in flight (retry_after)
    kNotReady,              ///< 503 starting up or shutting down
    kInsufficientStorage,   ///< 507 the disk is full; nothing was stored
    kStoredMeshDamaged,     ///< 500 the stored mesh and its tree are both damaged (detail says how)
    kUnknownScene,          ///< 404 no scene with that id, or no such (kept) revision of it
    kUnknownReference,    ///< 422 a scene names a mesh, geometry id or instance name that does not
                          ///< exist
    kMeshInUse,           ///< 409 a mesh that a scene's current revision uses cannot be deleted
    kStaleRevision,       ///< 412 If-Match names an older revision than the scene's current one
    kSceneMeshDeleted,    ///< 409 a kept scene revision uses a mesh that was deleted since
    kStoredSceneDamaged,  ///< 500 a stored scene revision is damaged (detail names the file)
};
/// The last ProblemKind (for loops over every kind).
inline constexpr ProblemKind kLastProblemKind = ProblemKind::kStoredSceneDamaged;

/// HTTP status of a kind (400, 401, 403, 404, 405, 408, 409, 412, 413, 415, 422, 431, 500, 503,
/// 507).
[[nodiscard]] int problem_status(ProblemKind kind) noexcept;
/// Short constant title, e.g. "Unknown mesh".
[[nodiscard]] std::string_view problem_title(ProblemKind kind) noexcept;
/// Stable type URI, e.g. "urn:kdrt:problem:unknown-mesh".
[[nodiscard]] std::string_view problem_type(ProblemKind kind) noexcept;

/// The reason phrase of an HTTP status (RFC 9110, e.g. "Not Found"), "" for one it does not
/// know.
[[nodiscard]] std::string_view http_reason_phrase(int status) noexcept;

/// One error reply.
struct Problem {
    ProblemKind kind = ProblemKind::kInternal;
    std::string detail;                   ///< what exactly is wrong, naming values and limits
    std::string instance;                 ///< the request path
    std::string code;                     ///< machine-readable sub-reason; empty = none
    std::optional<uint64_t> line;         ///< mesh parse errors in text: 1-based line
    std::optional<uint64_t> byte_offset;  ///< mesh parse errors in binary data
    std::optional<uint64_t> limit;        ///< the configured limit that was exceeded
    std::optional<uint32_t> retry_after;  ///< seconds (503)
    std::string request_id;
    /// Scene requests: the member at fault as the request spells it ("instances[3].transform"),
    /// and the instance (or pose entry) index.
    std::string field;
    std::optional<uint32_t> index;

    [[nodiscard]] int status() const noexcept { return problem_status(kind); }
};

/// The problem+json body of `problem`.
[[nodiscard]] std::string encode_problem(const Problem& problem);

/// Parses a problem+json body written by encode_problem (for clients and tests). Fails with a
/// message naming the first problem (not JSON, not an object, unknown type, missing detail).
[[nodiscard]] Result<Problem, std::string> decode_problem(std::string_view body);

/// Fixed phrases of the server's problem details; tests match on them.
namespace api_errors {
inline constexpr std::string_view kUnknownMesh = "no mesh with id";
inline constexpr std::string_view kBadMeshId = "is not a mesh id";
inline constexpr std::string_view kUnknownJob = "no job with id";
inline constexpr std::string_view kNoRoute = "no route for";
inline constexpr std::string_view kMethodNotAllowed = "does not support method";
inline constexpr std::string_view kUnsupportedMeshType = "cannot tell the mesh format";
inline constexpr std::string_view kUnsupportedRayType =
    "expects Content-Type application/x-kdrt-rays or application/json";
inline constexpr std::string_view kUnsupportedJsonType = "expects Content-Type application/json";
inline constexpr std::string_view kBodyTooLarge = "request body exceeds";
inline constexpr std::string_view kTooManyJsonRays = "rays in a JSON batch exceed";
inline constexpr std::string_view kEmptyMesh = "has no triangles";
inline constexpr std::string_view kBadJson = "invalid JSON";
inline constexpr std::string_view kMissingToken = "requires an Authorization: Bearer token";
inline constexpr std::string_view kWrongToken = "bearer token is not valid";
inline constexpr std::string_view kMissingRole = "needs a token with the role";
inline constexpr std::string_view kOverCapacity = "requests are in flight";
inline constexpr std::string_view kQueueFull = "render jobs are queued";
inline constexpr std::string_view kShuttingDown = "shutting down";
inline constexpr std::string_view kJobNotDone = "has no result";
}  // namespace api_errors

}  // namespace kdrt::proto
