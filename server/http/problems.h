#pragma once
/// Maps every error the server meets (proto decode errors, parse errors, cache errors) to the
/// RFC 9457 problem it is reported as. The HTTP status follows from the ProblemKind.

#include <string>

#include "kdrt/proto/json_api.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/problem.h"
#include "kdrt/proto/ray_batch.h"
#include "service.h"
#include "store/mesh_cache.h"
#include "store/scene_cache.h"

namespace kdrt::server {

[[nodiscard]] proto::Problem make_problem(proto::ProblemKind kind, std::string detail);
/// KDRR decode errors: 400 kBadRayBatch with `code`, except too_many_rays (413).
[[nodiscard]] proto::Problem ray_batch_problem(const proto::DecodeError& error);
/// Mesh files: 422 with `line` or `byte_offset`.
[[nodiscard]] proto::Problem mesh_parse_problem(const proto::ParseError& error);
/// JSON ray batches: 400, or 413 when over the ray limit.
[[nodiscard]] proto::Problem json_problem(const proto::JsonError& error, uint64_t max_rays);
/// Cache errors: 404 unknown mesh, 422 invalid mesh, 507 disk full, 500 stored-mesh-damaged,
/// 500 storage / internal.
[[nodiscard]] proto::Problem cache_problem(const CacheError& error);
/// 413 for a body over `limit` bytes.
[[nodiscard]] proto::Problem body_too_large_problem(uint64_t limit, const std::string& what);
/// 404 for an id that is not of the mesh id form or not stored.
[[nodiscard]] proto::Problem unknown_mesh_problem(const std::string& id);
/// A failed cache lookup of mesh `id`: unknown_mesh_problem(id) for an unknown mesh, else
/// cache_problem(error).
[[nodiscard]] proto::Problem mesh_lookup_problem(const CacheError& error, const std::string& id);
/// Scene errors: 404 unknown scene or revision, 400 invalid field, 422 unknown reference, 413
/// over max_instances / max_scenes, 412 stale revision, 409 a deleted mesh, 507, 500; with
/// `field` and `index` when the problem has them.
[[nodiscard]] proto::Problem scene_problem(const SceneProblem& error);
/// A scene request body refused by proto (400, or 413 over a limit, 422 an unknown reference),
/// naming the field and index.
[[nodiscard]] proto::Problem scene_request_problem(const proto::SceneRequestError& error,
                                                   uint32_t max_instances);
/// A refusal by batch_memory_budget of work needing `bytes`: 413 naming the budget when it could
/// never fit ("`subject` needs N bytes of memory, more than batch_memory_budget (L)`advice`"),
/// else 503 with Retry-After: 1 ("... hold H of L bytes (batch_memory_budget); `short_subject`
/// needs N; retry later"). An empty `short_subject` is `subject`.
[[nodiscard]] proto::Problem budget_problem(const ByteBudget& budget, uint64_t bytes,
                                            const std::string& subject, const std::string& advice,
                                            const std::string& short_subject = "");
/// 503 kNotReady with Retry-After: 1: "the server is shutting down", or when not
/// `shutting_down`, "the server is starting; retry shortly".
[[nodiscard]] proto::Problem not_ready_problem(bool shutting_down);

}  // namespace kdrt::server
