// POST /v1/meshes/{id}/intersect_all: KDRR -> KDRM (every hit along each ray) or KDRC (counts).

#include <span>

#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/httplib_internals.h"
#include "http/problems.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/text.h"
#include "kdrt/query.h"

namespace kdrt::server {

using proto::ProblemKind;

namespace {

constexpr const char* kAllHitsBodyWhat = "a KDRR batch (16 + 32 x max_rays)";

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
    const std::string type = proto::media_type_essence(req.get_header_value("Content-Type"));
    if (type != proto::kRaysMediaType) {
        discard_body(req, res, reader);
        return reply_problem(req, res,
                             make_problem(ProblemKind::kUnsupportedMediaType,
                                          "intersect_all expects Content-Type " +
                                              std::string(proto::kRaysMediaType) + ", not \"" +
                                              req.get_header_value("Content-Type") + "\""));
    }
    auto query = proto::parse_multi_hit_query(
        [&](std::string_view name) -> std::optional<std::string> {
            const std::string key(name);
            if (!req.has_param(key)) return std::nullopt;
            return req.get_param_value(key);
        },
        svc_.config.max_hits_per_ray);
    const std::string invalid = req.get_param_value("invalid_rays");
    if (query && !invalid.empty() && invalid != "refuse" && invalid != "miss") {
        query = proto::Err{"query parameter invalid_rays is " + proto::in_quotes(invalid) +
                           " (expected refuse or miss)"};
    }
    if (!query) {
        discard_body(req, res, reader);
        return reply_problem(req, res, make_problem(ProblemKind::kBadRequest, query.error()));
    }
    const std::shared_ptr<const KdTree> tree = acquire_tree(req, res, reader);
    if (!tree) return;
    // The batch's memory, its largest answer included, is taken from batch_memory_budget
    // before its body is read.
    const uint64_t body_limit = proto::kdrr_body_size(svc_.config.max_rays);
    const uint64_t declared = declared_body_bytes(req).value_or(body_limit);
    if (declared > body_limit) {
        discard_body(req, res, reader);
        return reply_problem(req, res, body_too_large_problem(body_limit, kAllHitsBodyWhat));
    }
    const uint64_t rays_at_most = declared / proto::kRayRecordBytes;
    const uint64_t bytes = 64 + rays_at_most * intersect_all_bytes_per_ray(*query);
    auto hold = svc_.batch_budget.try_take(bytes);
    if (!hold) {
        discard_body(req, res, reader);
        const uint64_t limit = svc_.batch_budget.limit();
        if (bytes > limit) {
            auto p = make_problem(
                ProblemKind::kPayloadTooLarge,
                "this batch of up to " + std::to_string(rays_at_most) + " rays with max_hits " +
                    std::to_string(query->max_hits) + " needs " + std::to_string(bytes) +
                    " bytes of memory, more than batch_memory_budget (" + std::to_string(limit) +
                    "); send fewer rays or a lower max_hits");
            p.limit = limit;
            return reply_problem(req, res, std::move(p));
        }
        auto p = make_problem(
            ProblemKind::kOverCapacity,
            "ray batches in flight hold " + std::to_string(svc_.batch_budget.held()) + " of " +
                std::to_string(limit) + " bytes (batch_memory_budget); this batch needs " +
                std::to_string(bytes) + "; retry later");
        p.retry_after = 1;
        p.limit = limit;
        return reply_problem(req, res, std::move(p));
    }
    auto body = read_body(req, res, reader, body_limit, body_limit, svc_.store.tmp_dir().string(),
                          kAllHitsBodyWhat);
    if (!body) return;
    request_context().bytes_in += body->size();
    auto batch = proto::decode_rays(
        body->bytes(), {.max_rays = svc_.config.max_rays, .reject_non_finite = invalid != "miss"});
    body.reset();
    if (!batch) return reply_problem(req, res, ray_batch_problem(batch.error()));
    if (batch->occlusion) {
        return reply_problem(
            req, res,
            make_problem(ProblemKind::kBadRequest,
                         "intersect_all takes a KDRR batch without the occlusion flag (bit 0 of "
                         "flags); occlusion queries go to /intersect"));
    }
    const std::span<const Ray> rays = batch->rays;
    request_context().rays = rays.size();
    svc_.metrics.add_rays(rays.size(), false);
    const KdTree& t = *tree;
    if (query->count_only) {
        std::vector<uint32_t> counts(rays.size());
        svc_.compute.run([&] { count_intersections(t, rays, query->merge_coincident, counts); });
        reply_bytes(res, proto::encode_hit_counts(counts), proto::kHitCountMediaType);
    } else {
        const AllHitsOptions options{query->max_hits, query->merge_coincident};
        AllHits all = svc_.compute.run([&] { return kdrt::intersect_all(t, rays, options); });
        std::vector<Vec3> normals(query->layout.normal ? all.hits.size() : 0);
        std::vector<Vec3> points(query->layout.point ? all.hits.size() : 0);
        if (!normals.empty() || !points.empty())
            svc_.compute.run([&] { hit_attributes(t, all.hits, normals, points); });
        proto::MultiHitsView view;
        view.layout = query->layout;
        view.merged = query->merge_coincident;
        view.max_hits = query->max_hits;
        view.offsets = all.offsets;
        view.counts = all.counts;
        view.hits = all.hits;
        view.normals = normals;
        view.points = points;
        std::vector<std::byte> answer = proto::encode_multi_hits(view);
        all = {};
        reply_bytes(res, std::move(answer), proto::kMultiHitMediaType);
    }
    keep_until_sent(res, std::make_shared<ByteBudget::Hold>(std::move(*hold)));
}

std::shared_ptr<const KdTree> Routes::acquire_tree(const httplib::Request& req,
                                                   httplib::Response& res,
                                                   const httplib::ContentReader& reader) {
    const std::string id = req.matches[1];
    auto tree = svc_.cache.acquire(id);
    if (tree) return std::move(tree).value();
    discard_body(req, res, reader);
    reply_problem(req, res, mesh_lookup_problem(tree.error(), id));
    return nullptr;
}

}  // namespace kdrt::server
