#include "http/problems.h"

#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/text.h"

namespace kdrt::server {

using proto::in_quotes;
using proto::ProblemKind;

proto::Problem make_problem(ProblemKind kind, std::string detail) {
    proto::Problem p;
    p.kind = kind;
    p.detail = std::move(detail);
    return p;
}

proto::Problem ray_batch_problem(const proto::DecodeError& error) {
    const bool too_many = error.code == proto::DecodeErrorCode::kTooManyRays;
    proto::Problem p =
        make_problem(too_many ? ProblemKind::kPayloadTooLarge : ProblemKind::kBadRayBatch,
                     "malformed KDRR batch: " + error.detail);
    p.code = std::string(proto::decode_error_code_name(error.code));
    return p;
}

proto::Problem mesh_parse_problem(const proto::ParseError& error) {
    proto::Problem p = make_problem(ProblemKind::kMeshParseError, error.message);
    if (error.line) p.line = error.line;
    if (error.byte_offset || error.message.rfind("byte ", 0) == 0)
        p.byte_offset = error.byte_offset;
    return p;
}

proto::Problem json_problem(const proto::JsonError& error, uint64_t max_rays) {
    if (error.code == proto::JsonError::Code::kTooMany) {
        proto::Problem p = make_problem(ProblemKind::kPayloadTooLarge, error.detail);
        p.limit = max_rays;
        return p;
    }
    return make_problem(ProblemKind::kBadRequest, error.detail);
}

proto::Problem cache_problem(const CacheError& error) {
    switch (error.code) {
        case CacheError::Code::kUnknownMesh:
            return make_problem(ProblemKind::kUnknownMesh, error.detail);
        case CacheError::Code::kInvalidMesh:
            return make_problem(ProblemKind::kInvalidMesh, error.detail);
        case CacheError::Code::kDamaged:
            return make_problem(ProblemKind::kStoredMeshDamaged, error.detail);
        case CacheError::Code::kNoSpace:
            return make_problem(ProblemKind::kInsufficientStorage, error.detail);
        case CacheError::Code::kStorage:
        case CacheError::Code::kInternal:
            break;
    }
    return make_problem(ProblemKind::kInternal, error.detail);
}

proto::Problem body_too_large_problem(uint64_t limit, const std::string& what) {
    proto::Problem p =
        make_problem(ProblemKind::kPayloadTooLarge, std::string(proto::api_errors::kBodyTooLarge) +
                                                        " the limit of " + std::to_string(limit) +
                                                        " bytes for " + what);
    p.limit = limit;
    return p;
}

proto::Problem unknown_mesh_problem(const std::string& id) {
    if (!proto::is_mesh_id(id))
        return make_problem(ProblemKind::kUnknownMesh,
                            in_quotes(id) + " " + std::string(proto::api_errors::kBadMeshId) +
                                " (64 lower-case hex digits)");
    return make_problem(ProblemKind::kUnknownMesh,
                        std::string(proto::api_errors::kUnknownMesh) + " " + id);
}

proto::Problem mesh_lookup_problem(const CacheError& error, const std::string& id) {
    return error.code == CacheError::Code::kUnknownMesh ? unknown_mesh_problem(id)
                                                        : cache_problem(error);
}

proto::Problem not_ready_problem(bool shutting_down) {
    proto::Problem p = make_problem(
        ProblemKind::kNotReady,
        shutting_down ? "the server is " + std::string(proto::api_errors::kShuttingDown)
                      : std::string("the server is starting; retry shortly"));
    p.retry_after = 1;
    return p;
}

}  // namespace kdrt::server
