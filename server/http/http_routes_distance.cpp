// POST /v1/meshes/{id}/distance: KDRP query points -> KDRD closest points (kdrt/distance.h).

#include <span>

#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/httplib_internals.h"
#include "http/problems.h"
#include "kdrt/distance.h"
#include "kdrt/proto/distance.h"

namespace kdrt::server {

using proto::ProblemKind;

namespace {

constexpr const char* kDistanceBodyWhat = "a KDRP batch (16 + 12 x max_distance_points)";

/// The body and the decoded points (12 + 12), the engine's answers and the encoded ones (32 + 32).
constexpr uint64_t kBytesPerPoint = 88;

proto::Problem point_batch_problem(const proto::DecodeError& error, uint32_t limit) {
    const bool too_many = error.code == proto::DecodeErrorCode::kTooManyRays;
    proto::Problem p = make_problem(
        too_many ? ProblemKind::kPayloadTooLarge : ProblemKind::kBadRequest,
        "malformed KDRP batch: " + error.detail + (too_many ? " (max_distance_points)" : ""));
    p.code = std::string(proto::decode_error_code_name(error.code));
    if (too_many) p.limit = limit;
    return p;
}

/// The X-Kdrt-Surface header: whether signs can be decided on this mesh, and if not why.
std::string surface_text(const SurfaceIndex& index) {
    if (index.closed) return "closed";
    return "not closed: " + std::to_string(index.boundary_edges) + " boundary edges, " +
           std::to_string(index.nonmanifold_edges) + " non-manifold edges, " +
           std::to_string(index.misoriented_edges) + " misoriented edges";
}

}  // namespace

void Routes::distance(const httplib::Request& req, httplib::Response& res,
                      const httplib::ContentReader& reader) {
    const std::string type = proto::media_type_essence(req.get_header_value("Content-Type"));
    if (type != proto::kPointMediaType) {
        discard_body(req, res, reader);
        return reply_problem(
            req, res,
            make_problem(ProblemKind::kUnsupportedMediaType,
                         "distance expects Content-Type " + std::string(proto::kPointMediaType) +
                             ", not \"" + req.get_header_value("Content-Type") + "\""));
    }
    auto query =
        proto::parse_distance_query([&](std::string_view name) -> std::optional<std::string> {
            const std::string key(name);
            if (!req.has_param(key)) return std::nullopt;
            return req.get_param_value(key);
        });
    if (!query) {
        discard_body(req, res, reader);
        return reply_problem(req, res, make_problem(ProblemKind::kBadRequest, query.error()));
    }
    const std::shared_ptr<const KdTree> tree = acquire_tree(req, res, reader);
    if (!tree) return;
    const uint32_t max_points = svc_.config.max_distance_points;
    const uint64_t body_limit = proto::kdrp_body_size(max_points);
    const uint64_t declared = declared_body_bytes(req).value_or(body_limit);
    if (declared > body_limit) {
        discard_body(req, res, reader);
        return reply_problem(req, res, body_too_large_problem(body_limit, kDistanceBodyWhat));
    }
    auto hold = take_budget_bytes(req, res, reader,
                                  64 + declared / proto::kPointRecordBytes * kBytesPerPoint);
    if (!hold) return;
    auto body = read_body(req, res, reader, body_limit, body_limit, svc_.store.tmp_dir().string(),
                          kDistanceBodyWhat);
    if (!body) return;
    request_context().bytes_in += body->size();
    auto points =
        proto::decode_points(body->bytes(), {.max_rays = max_points, .reject_non_finite = true});
    body.reset();
    if (!points) return reply_problem(req, res, point_batch_problem(points.error(), max_points));
    request_context().rays = points->size();
    std::shared_ptr<const SurfaceIndex> index;
    std::vector<ClosestPoint> answers(points->size());
    const DistanceOptions options{query->max_distance, query->signed_query};
    svc_.compute.run([&] {
        index = svc_.cache.surface_index(req.matches[1], tree);
        closest_points(*tree, *index, *points, answers, options);
    });
    res.set_header("X-Kdrt-Surface", surface_text(*index));
    reply_bytes(res, proto::encode_distances(answers, query->signed_query),
                proto::kDistanceMediaType);
    keep_until_sent(res, std::make_shared<ByteBudget::Hold>(std::move(*hold)));
}

}  // namespace kdrt::server
