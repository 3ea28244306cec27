#include "http/problems.h"

#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/text.h"

namespace kdrt::server {

using proto::ProblemKind;
using proto::quote_value;

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
                            quote_value(id) + " " + std::string(proto::api_errors::kBadMeshId) +
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

proto::Problem scene_problem(const SceneProblem& error) {
    using Code = SceneProblem::Code;
    ProblemKind kind = ProblemKind::kInternal;
    switch (error.code) {
        case Code::kUnknownScene:
        case Code::kUnknownRevision:
            kind = ProblemKind::kUnknownScene;
            break;
        case Code::kInvalid:
            kind = ProblemKind::kBadRequest;
            break;
        case Code::kUnknownReference:
            kind = ProblemKind::kUnknownReference;
            break;
        case Code::kTooLarge:
            kind = ProblemKind::kPayloadTooLarge;
            break;
        case Code::kStale:
            kind = ProblemKind::kStaleRevision;
            break;
        case Code::kMeshGone:
            kind = ProblemKind::kSceneMeshDeleted;
            break;
        case Code::kNoSpace:
            kind = ProblemKind::kInsufficientStorage;
            break;
        case Code::kDamaged:
            kind = ProblemKind::kStoredSceneDamaged;
            break;
        case Code::kInternal:
            kind = ProblemKind::kInternal;
            break;
    }
    proto::Problem p = make_problem(kind, error.detail);
    p.field = error.field;
    p.index = error.index;
    p.limit = error.limit;
    return p;
}

proto::Problem scene_request_problem(const proto::SceneRequestError& error,
                                     uint32_t max_instances) {
    const ProblemKind kind = error.over_limit          ? ProblemKind::kPayloadTooLarge
                             : error.unknown_reference ? ProblemKind::kUnknownReference
                                                       : ProblemKind::kBadRequest;
    proto::Problem p = make_problem(kind, error.detail);
    p.field = error.field;
    p.index = error.index;
    if (error.over_limit) p.limit = max_instances;
    return p;
}

proto::Problem budget_problem(const ByteBudget& budget, uint64_t bytes, const std::string& subject,
                              const std::string& advice, const std::string& short_subject) {
    const uint64_t limit = budget.limit();
    if (bytes > limit) {
        auto p = make_problem(proto::ProblemKind::kPayloadTooLarge,
                              subject + " needs " + std::to_string(bytes) +
                                  " bytes of memory, more than batch_memory_budget (" +
                                  std::to_string(limit) + ")" + advice);
        p.limit = limit;
        return p;
    }
    auto p = make_problem(proto::ProblemKind::kOverCapacity,
                          "ray batches in flight hold " + std::to_string(budget.held()) + " of " +
                              std::to_string(limit) + " bytes (batch_memory_budget); " +
                              (short_subject.empty() ? subject : short_subject) + " needs " +
                              std::to_string(bytes) + "; retry later");
    p.retry_after = 1;
    p.limit = limit;
    return p;
}

}  // namespace kdrt::server
