// POST /v1/meshes/{id}/distance: KDRP query points -> KDRD closest points (kdrt/distance.h), and
// what the scene form (http_routes_scenes.cpp) shares with it: the points' body and the batch's
// work limit and cancellation.

#include <atomic>
#include <functional>
#include <optional>
#include <span>
#include <vector>

#include "core/log.h"
#include "http/http_front.h"
#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/problems.h"
#include "kdrt/distance.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/text.h"

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

/// A batch whose work (cells visited + triangles tested) passes max_distance_work: refused when
/// its point count alone does (`work` 0), or stopped when its search did.
proto::Problem distance_work_problem(uint64_t limit, uint64_t work, size_t points) {
    auto p = make_problem(
        ProblemKind::kBadRequest,
        work == 0 ? std::to_string(points) + " points exceed max_distance_work " +
                        std::to_string(limit) + " (every point costs at least 1)"
                  : "distance work (cells visited + triangles tested) passed max_distance_work " +
                        std::to_string(limit) + " for " + std::to_string(points) +
                        " points; stopped. Points very far from the mesh (about 1e13 of its "
                        "size) cost the most: send fewer points per request");
    p.limit = limit;
    return p;
}

}  // namespace

std::optional<std::vector<Vec3>> Routes::read_points(const httplib::Request& req,
                                                     httplib::Response& res,
                                                     const httplib::ContentReader& reader,
                                                     uint64_t memory_per_point) {
    const uint32_t max_points = svc_.config.max_distance_points;
    auto body = read_batch(req, res, reader,
                           {.limit = proto::kdrp_body_size(max_points),
                            .what = kDistanceBodyWhat,
                            .record_bytes = proto::kPointRecordBytes,
                            .memory_per_record = memory_per_point,
                            .records = "points",
                            .advice = "; send fewer points"});
    if (!body) return std::nullopt;
    auto points =
        proto::decode_points(body->bytes(), {.max_rays = max_points, .reject_non_finite = true});
    body.reset();
    if (!points) {
        reply_problem(req, res, point_batch_problem(points.error(), max_points));
        return std::nullopt;
    }
    request_context().rays = points->size();
    const uint64_t max_work = svc_.config.max_distance_work;
    if (points->size() > max_work) {  // every point visits at least the root cell
        reply_problem(req, res, distance_work_problem(max_work, 0, points->size()));
        return std::nullopt;
    }
    return std::move(points).value();
}

bool Routes::run_distance(const httplib::Request& req, httplib::Response& res, size_t points,
                          const std::function<DistanceStats(const DistanceControl&)>& search) {
    // Stopped when the client goes away (checked about every millisecond of work) or the work
    // passes max_distance_work, as renders are.
    const uint64_t max_work = svc_.config.max_distance_work;
    std::atomic<bool> cancel{false};
    DistanceControl control;
    control.cancel = &cancel;
    control.max_work = max_work;
    control.poll = [gone = client_gone_check(), &cancel] {
        if (gone()) cancel = true;
    };
    const DistanceStats stats = svc_.compute.run([&] { return search(control); });
    if (stats.status == DistanceStatus::kCancelled) {
        log_event(LogLevel::kInfo, "distance cancelled: the client closed the connection",
                  {{"id", request_context().request_id}});
        res.set_header("Connection", "close");
        reply_problem(req, res,
                      make_problem(ProblemKind::kBadRequest,
                                   "the client closed the connection; distance cancelled"));
        return false;
    }
    if (stats.status == DistanceStatus::kOverWork) {
        reply_problem(req, res, distance_work_problem(max_work, stats.work, points));
        return false;
    }
    return true;
}

void Routes::distance(const httplib::Request& req, httplib::Response& res,
                      const httplib::ContentReader& reader) {
    if (!has_media_type(req, res, proto::kPointMediaType, "distance")) return;
    auto query = proto::parse_distance_query(query_params(req));
    if (!query)
        return reply_problem(req, res, make_problem(ProblemKind::kBadRequest, query.error()));
    const std::shared_ptr<const KdTree> tree = acquire_tree(req, res);
    if (!tree) return;
    const auto points = read_points(req, res, reader, kBytesPerPoint);
    if (!points) return;
    std::shared_ptr<const SurfaceIndex> index;
    std::vector<ClosestPoint> answers(points->size());
    const DistanceOptions options{query->max_distance, query->signed_query};
    const bool done = run_distance(req, res, points->size(), [&](const DistanceControl& control) {
        index = svc_.cache.surface_index(req.matches[1], tree);
        return closest_points(*tree, *index, *points, answers, options, control);
    });
    if (!done) return;
    res.set_header("X-Kdrt-Surface", surface_text(*index));
    reply_bytes(res, proto::encode_distances(answers, query->signed_query),
                proto::kDistanceMediaType);
}

}  // namespace kdrt::server
