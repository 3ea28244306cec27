// POST /v1/meshes/{id}/intersect: KDRR -> KDRH/KDRO, or JSON -> JSON.

#include <algorithm>

#include "http_routes.h"
#include "http_util.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/ray_batch.h"
#include "problems.h"

namespace kdrt::server {

using proto::ProblemKind;

void Routes::intersect(const httplib::Request& req, httplib::Response& res, const httplib::ContentReader& reader) {
    const std::string type = proto::media_type_essence(req.get_header_value("Content-Type"));
    const bool binary = type == proto::kRaysMediaType;
    if (!binary && type != proto::kJsonMediaType) {
        discard_body(req, res, reader);
        return reply_problem(req, res,
                             make_problem(ProblemKind::kUnsupportedMediaType,
                                          "intersect " + std::string(proto::api_errors::kUnsupportedRayType) +
                                              ", not \"" + req.get_header_value("Content-Type") + "\""));
    }
    const std::string id = req.matches[1];
    auto tree = svc_.cache.acquire(id);
    if (!tree) {
        discard_body(req, res, reader);
        return reply_problem(req, res,
                             tree.error().code == CacheError::Code::kUnknownMesh ? unknown_mesh_problem(id)
                                                                                 : cache_problem(tree.error()));
    }
    if (binary) return intersect_binary(req, res, reader, **tree);
    intersect_json(req, res, reader, **tree);
}

void Routes::intersect_binary(const httplib::Request& req, httplib::Response& res, const httplib::ContentReader& reader,
                              const KdTree& tree) {
    const uint64_t limit = proto::kBatchHeaderBytes + uint64_t{proto::kRayRecordBytes} * svc_.config.max_rays;
    const uint64_t declared = std::min(req.get_header_value<uint64_t>("Content-Length"), limit);
    auto body = read_body(req, res, reader, limit, limit, svc_.store.tmp_dir().string(),
                          "a KDRR batch (16 + 32 x max_rays)", svc_.byte_pool.take(declared));
    if (!body) return;
    auto batch = proto::decode_rays(body->bytes(), {.max_rays = svc_.config.max_rays, .reject_non_finite = true});
    svc_.byte_pool.give(body->release_buffer());
    body.reset();
    if (!batch) return reply_problem(req, res, ray_batch_problem(batch.error()));
    request_context().rays = batch->rays.size();
    svc_.metrics.add_rays(batch->rays.size(), batch->occlusion);
    if (batch->occlusion) {
        std::vector<uint8_t> occluded(batch->rays.size());
        svc_.compute.occluded(tree, batch->rays, occluded);
        return reply_bytes(res, proto::encode_occlusion(occluded), proto::kOcclusionMediaType, &svc_.byte_pool);
    }
    std::vector<Hit> hits = svc_.hit_pool.take(batch->rays.size());
    hits.resize(batch->rays.size());
    svc_.compute.intersect(tree, batch->rays, hits);
    std::vector<std::byte> answer = proto::encode_hits(hits);
    svc_.hit_pool.give(std::move(hits));
    reply_bytes(res, std::move(answer), proto::kHitsMediaType, &svc_.byte_pool);
}

void Routes::intersect_json(const httplib::Request& req, httplib::Response& res, const httplib::ContentReader& reader,
                            const KdTree& tree) {
    auto body = read_body(req, res, reader, svc_.config.max_json_bytes, svc_.config.max_json_bytes,
                          svc_.store.tmp_dir().string(), "a JSON request (max_json_bytes)");
    if (!body) return;
    auto request = proto::decode_json_rays(as_text(body->bytes()), svc_.config.max_json_rays);
    body.reset();
    if (!request) return reply_problem(req, res, json_problem(request.error(), svc_.config.max_json_rays));
    request_context().rays = request->rays.size();
    svc_.metrics.add_rays(request->rays.size(), request->occlusion);
    if (request->occlusion) {
        std::vector<uint8_t> occluded(request->rays.size());
        svc_.compute.occluded(tree, request->rays, occluded);
        return reply_json(res, 200, proto::encode_json_occlusion(occluded));
    }
    std::vector<Hit> hits(request->rays.size());
    svc_.compute.intersect(tree, request->rays, hits);
    reply_json(res, 200, proto::encode_json_hits(hits));
}

}  // namespace kdrt::server
