// POST /v1/meshes/{id}/intersect_all: KDRR -> KDRM (every hit along each ray) or KDRC (counts).

#include <span>

#include "http/http_front.h"
#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/problems.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/text.h"
#include "kdrt/query.h"

namespace kdrt::server {

using proto::ProblemKind;

namespace {

constexpr const char* kAllHitsBodyWhat = "a KDRR batch (16 + 32 x max_rays)";

/// The query parameters of an intersect_all request (proto::parse_multi_hit_query, and
/// invalid_rays: refuse or miss).
proto::Result<proto::MultiHitQuery, std::string> multi_hit_query(const httplib::Request& req,
                                                                 uint32_t max_hits) {
    auto query = proto::parse_multi_hit_query(query_params(req), max_hits);
    const std::string invalid = req.get_param_value("invalid_rays");
    if (query && !invalid.empty() && invalid != "refuse" && invalid != "miss")
        return proto::Err{"query parameter invalid_rays is " + proto::quote_value(invalid) +
                          " (expected refuse or miss)"};
    return query;
}

proto::Problem occlusion_refused() {
    return make_problem(ProblemKind::kBadRequest,
                        "intersect_all takes a KDRR batch without the occlusion flag (bit 0 of "
                        "flags); occlusion queries go to /intersect");
}

/// Every hit along each ray, with the normals and points the query asks for, encoded (KDRM).
std::vector<std::byte> all_hits_answer(Compute& compute, const KdTree& tree,
                                       std::span<const Ray> rays,
                                       const proto::MultiHitQuery& query) {
    const AllHitsOptions options{query.max_hits, query.merge_coincident};
    AllHits all = compute.run([&] { return kdrt::intersect_all(tree, rays, options); });
    std::vector<Vec3> normals(query.layout.normal ? all.hits.size() : 0);
    std::vector<Vec3> points(query.layout.point ? all.hits.size() : 0);
    if (!normals.empty() || !points.empty())
        compute.run([&] { hit_attributes(tree, all.hits, normals, points); });
    proto::MultiHitsView view;
    view.layout = query.layout;
    view.merged = query.merge_coincident;
    view.max_hits = query.max_hits;
    view.offsets = all.offsets;
    view.counts = all.counts;
    view.hits = all.hits;
    view.normals = normals;
    view.points = points;
    return proto::encode_multi_hits(view);
}

}  // namespace

uint64_t intersect_all_bytes_per_ray(const proto::MultiHitQuery& q) noexcept {
    // The body and the decoded rays (32 + 32); the engine's offsets and counts and the encoded
    // ones (12 + 12); per kept hit the engine's two copies (per block, then gathered), the normal
    // and point when asked for, and the encoded record.
    if (q.count_only) return 32 + 32 + 4 + 4;
    return 88 + uint64_t{q.max_hits} * (32 + 24 + proto::hit_record_bytes(q.layout));
}

void Routes::intersect_all(const httplib::Request& req, httplib::Response& res,
                           const httplib::ContentReader& reader) {
    if (!has_media_type(req, res, proto::kRaysMediaType, "intersect_all")) return;
    const std::string invalid = req.get_param_value("invalid_rays");
    auto query = multi_hit_query(req, svc_.config.max_hits_per_ray);
    if (!query)
        return reply_problem(req, res, make_problem(ProblemKind::kBadRequest, query.error()));
    const std::shared_ptr<const KdTree> tree = acquire_tree(req, res);
    if (!tree) return;
    // The batch's memory, its largest answer included, is held from before its body is read.
    auto body = read_batch(req, res, reader,
                           {.limit = proto::kdrr_body_size(svc_.config.max_rays),
                            .what = kAllHitsBodyWhat,
                            .record_bytes = proto::kRayRecordBytes,
                            .memory_per_record = intersect_all_bytes_per_ray(*query),
                            .records = "rays with max_hits " + std::to_string(query->max_hits),
                            .advice = "; send fewer rays or a lower max_hits"});
    if (!body) return;
    auto batch = proto::decode_rays(
        body->bytes(), {.max_rays = svc_.config.max_rays, .reject_non_finite = invalid != "miss"});
    body.reset();
    if (!batch) return reply_problem(req, res, ray_batch_problem(batch.error()));
    if (batch->occlusion) return reply_problem(req, res, occlusion_refused());
    request_context().rays = batch->rays.size();
    svc_.metrics.add_rays(batch->rays.size(), false);
    if (query->count_only) {
        std::vector<uint32_t> counts(batch->rays.size());
        svc_.compute.run(
            [&] { count_intersections(*tree, batch->rays, query->merge_coincident, counts); });
        return reply_bytes(res, proto::encode_hit_counts(counts), proto::kHitCountMediaType);
    }
    reply_bytes(res, all_hits_answer(svc_.compute, *tree, batch->rays, *query),
                proto::kMultiHitMediaType);
}

}  // namespace kdrt::server
